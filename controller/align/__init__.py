"""Probe-and-align before repair (Padathu 2005; docs/contract.md §4).

fit, bestfit, leveling and kinematics are pure math; probe_cycle talks to the CNC; routine runs
the whole `cell align run`; report writes its JSON and PNG.
"""
