"""fsswarp: forward-scan sonar synthesis, space carving, depth/tilt estimation and ghost removal."""

__version__ = "0.1.0"
