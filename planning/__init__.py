"""Where to look and what was found: the planner's pieces above the pure map.

Instance tracking (:mod:`planning.instances`), look-next goals (:mod:`planning.look_next`),
best rays and triangulated estimates beyond the map (:mod:`planning.beyond`) and occupancy
answers for planners (:mod:`planning.occupancy_queries`), and the fleet search's allocation of
look-next goals across robots (:mod:`planning.fleet_allocation`). Pure computation like the map (no I/O,
no Zenoh, no threads); it reads the map only through ``RayFrontsMap``'s public API and the
arrays the search hands it. World frame, metres, z up.

The ``grid`` the occupancy functions and :func:`planning.look_next.look_next` read is
``RayFrontsMap.occupancy_view()``: a read-only :class:`semantic_map.OccupancyView` (int8
log-odds, ``> 0`` occupied, ``< 0`` free, ``0`` unknown; ``ijk = floor(xyz / vox)``), the same
object while the map's grid is the same one, so the caches here key on it and its ``revision``.
"""
