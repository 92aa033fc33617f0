"""Closed-loop object search in the synthetic world (planned CLI: ``rayfronts eval search``).

Work in progress: ``planner`` (grid A* through known free space), ``robot`` (platforms, camera
poses, true-world collision checks, true free grid for the oracle), ``metrics`` (SPL, summaries)
and ``episode`` (a geometric frontier-exploration episode in process) exist; semantic policies,
missions, CLI, reports and the distributed mode do not yet.
"""
