"""The test suite: one folder per room of the code (docs/testing.md)."""
