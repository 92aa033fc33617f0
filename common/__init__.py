"""Shared by edge, mapper and query client: conventions, geometry, config, wire codec,
Zenoh helpers, the key space, the synthetic world. Imports none of the other parts."""
