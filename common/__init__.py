"""Shared by edge, mapper and query client: conventions, geometry, config, wire codec,
Zenoh helpers, the key space, messages (docs/). Imports none of the other parts."""
