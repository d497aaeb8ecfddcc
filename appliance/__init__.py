"""fluorosim: the fluoroscopy training appliance (everything that is not a hardware driver)."""

__version__ = "0.1.0"
