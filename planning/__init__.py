"""Where to look and what was found: the planner's pieces above the pure map.

Instance tracking (:mod:`planning.instances`), look-next goals (:mod:`planning.look_next`),
best rays and triangulated estimates beyond the map (:mod:`planning.beyond`) and occupancy
answers for planners (:mod:`planning.occupancy_queries`), and the fleet search's allocation of
look-next goals across robots (:mod:`planning.fleet_allocation`). Pure computation like the map (no I/O,
no Zenoh, no threads); it reads the map only through ``RayFrontsMap``'s public API and the
arrays the search hands it. World frame, metres, z up.
"""
