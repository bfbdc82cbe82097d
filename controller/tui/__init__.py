"""The operator's terminal UI (Textual): a view over the controller's snapshots and commands."""
