"""The factory interface (DESIGN.md §8): the cell's state, process values, job and alarms over OPC UA."""
