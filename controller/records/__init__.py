"""The shop's record store (docs/contract.md §9, docs/records.md): every build's record in one SQL
database (SQLite for a shop file, PostgreSQL the reference), queued in its run directory while the
database cannot be reached, queried by `cell records query`."""
