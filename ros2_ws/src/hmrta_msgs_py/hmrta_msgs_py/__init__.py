"""HMRTA message layer: payload codecs (``codec``), topic names and QoS profiles (``topics``),
shared process plumbing (``runtime``) and the console scripts' body (``console``).

Importing the package itself loads nothing (every console script passes through it before its
Ctrl-C handling is in place: ``console``)."""
