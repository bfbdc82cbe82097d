"""The factory interface (docs/contract.md §8): the cell's state, process values, job and alarms over OPC UA."""
