"""Tests of opcua."""
