from . import rotation_conversions  # noqa: F401
