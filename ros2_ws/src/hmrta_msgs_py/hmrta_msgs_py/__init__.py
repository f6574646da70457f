"""HMRTA message layer: payload codecs (``codec``), topic names and QoS profiles (``topics``),
and shared process plumbing (``runtime``)."""
from .codec import DecodeError  # noqa: F401
