"""Neutral core shared by every layer: base errors, the configuration schema and loader, units."""
