"""Time, state and safety: configuration, the build state machine, alignment, journal, CLI, TUI."""
