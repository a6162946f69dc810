"""``transport``: collective transport via sequential caging (Varadharajan, Soma, Beltrame)."""
from .behaviour import Transport
from .params import TransportParams

__all__ = ["Transport", "TransportParams"]
