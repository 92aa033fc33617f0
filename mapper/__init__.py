"""Base-station part: the mapper process around the RayFronts map (``semantic_map``):
ingest, queries, layers, snapshots, fleet and shards, outputs."""
