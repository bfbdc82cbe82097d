"""One module per device and transport, each behind a small typed interface. Drivers take a URL."""
