"""The `cell` command line: one module per subcommand group, registered in main.py."""
