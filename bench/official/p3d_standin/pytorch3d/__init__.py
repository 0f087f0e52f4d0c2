"""Stand-in package (see transforms/rotation_conversions.py)."""
