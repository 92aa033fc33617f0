"""Base-station part: the RayFronts map (occupancy, semantic voxels, frontiers, ray
frontiers), queries, snapshots, the mapper process, evaluation."""
