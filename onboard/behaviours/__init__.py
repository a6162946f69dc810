"""Shipped behaviours; importing this package registers them."""
from . import aggregate, transport  # noqa: F401
