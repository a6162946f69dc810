"""``transport``: collective transport via sequential caging (Varadharajan, Soma, Beltrame)."""
from .params import TransportParams
from .behaviour import Transport

__all__ = ["Transport", "TransportParams"]
