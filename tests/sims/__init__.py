"""Tests of sims."""
