"""Closed-loop object search in the synthetic world (``rayfronts eval search``).

Data flows one way per step: ``sensing`` (views rendered at the robot's pose through the edge
chain: encoder → PCA → wire) → ``world_model`` (the mapper's map and search answering, in
process) → ``policies`` (where to go, what to declare) → ``navigation`` / ``planner`` (paths
through known free space, scipy Dijkstra / A*) → ``robot`` (motion, true-world collision
checks). ``missions`` draws tasks and their true shortest paths, ``metrics`` SPL,
``episode`` runs one episode, ``evaluate`` a whole run and its outputs, ``recording`` one
episode as a rerun file. The distributed mode (real processes over Zenoh) does not exist yet.
"""
