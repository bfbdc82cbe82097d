"""One simulator per device, speaking the driver's wire protocol byte for byte."""
