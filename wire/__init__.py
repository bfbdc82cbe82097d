"""Wire codecs and signal maps shared by the drivers and the simulators (bytes and registers only)."""
