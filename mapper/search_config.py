"""Config section ``search.*`` of ``rayfronts mapper``: the planners' search service
(:mod:`mapper.search_server`). Lengths in metres, angles in degrees."""
from __future__ import annotations

from dataclasses import dataclass

from common.config import ConfigError, field_
from mapper.leases import StandingLimits

DEFAULT_BACKGROUND = ["building", "road", "ground", "tree", "sky"]


#: the values of ``search.ray_evidence``
RAY_EVIDENCE = ("distinct", "margin")


@dataclass
class SearchSection(StandingLimits):
    background: list[str] = field_(list(DEFAULT_BACKGROUND),
                                    "phrases a search's targets are softmaxed against when the request names none "
                                    "(the paper's querying: probabilities over targets + background)")
    temperature: float = field_(100.0, "softmax temperature of search scores (the paper's 100)")
    min_instance_voxels: int = field_(3, "voxel groups smaller than this are not reported as instances")
    max_trackers: int = field_(64, "instance identity trackers kept (one per target phrase or embedding); the least "
                                   "recently used is dropped (its objects get new ids if searched again)")
    identity_threshold: float = field_(0.5, "an object's identity follows the voxels whose probability for its "
                                            "target over the target + search.background is above this, whatever "
                                            "a request's threshold, background or other targets (docs/identity.md)")
    instance_grace: int = field_(2, "map updates an object may go unseen (below identity_threshold) and still come "
                                    "back with its id; after that it is lost (event 'lost')")
    ray_radius_m: float = field_(0.0, "rays attached within this distance of a frontier support it; 0 = the "
                                      "frontier cell size")
    standoff_m: float = field_(1.0, "a look-next viewpoint lies within this distance of its frontier")
    sensing_radius_m: float = field_(3.0, "unknown volume within this radius of a viewpoint is its gain")
    ray_cosine_resolution: float = field_(2.0 ** -11, "a ray's cosine to what sets a target apart (ray_z's evidence) "
                                                    "within this of the median ray's is not an outlier (ray_z 0): "
                                                    "the features cross the wire as float16, whose rounding moves "
                                                    "a cosine by up to ~2^-11; 0 = off")
    distinct_phrases: int = field_(0, "ray_z's evidence is a ray's cosine to what sets a target apart from its this "
                                      "many nearest other phrases (by text embedding; the others explain nothing "
                                      "of it); 0 = every other phrase. Set it (e.g. 8) for a large background: a "
                                      "vocabulary of a hundred phrases explains the whole target and leaves none")
    ray_evidence: str = field_("distinct", "what ray_z z-scores: 'distinct', a ray's cosine to what sets the target "
                                           "apart from its search.distinct_phrases nearest other phrases, or 'margin', "
                                           "its cosine to the target less its best cosine to those phrases (a ray "
                                           "toward a similar class reads below the sky's)")
    beyond_rays: int = field_(20, "best rays per target considered for triangulation")
    max_gap_m: float = field_(2.0, "two rays triangulate when they pass within this distance")
    angle_err_deg: float = field_(0.0, "direction uncertainty of a ray (estimate radius); 0 = half the map's "
                                       "angle bin")
    lock_timeout_s: float = field_(2.0, "a search waits at most this long for the map lock to read occupancy and "
                                        "frontiers; after that it answers without look_next (timings_ms.stale=1)")
    max_occupancy_cells: int = field_(4_000_000, "cells an occupancy request may return")
    fleet_footprint_m: float = field_(0.0, "a fleet search keeps its robots' goal viewpoints at least this far apart "
                                           "(no two robots sent to one frontier region); 0 = twice "
                                           "search.sensing_radius_m (the sensed spheres do not overlap)")
    fleet_unreachable_tol_m: float = field_(1.0, "a robot that reported a position unreachable gets no fleet goal "
                                                 "within this distance of it")
    fleet_unreachable_max: int = field_(32, "unreachable positions kept per robot (the oldest is forgotten)")
    fleet_unreachable_ttl_s: float = field_(600.0, "an unreachable position is forgotten after this long (s): the "
                                                   "map, and the way there, change")
    warm_up: bool = field_(True, "load the text model and embed the background phrases in the background as soon "
                                 "as the map's feature space is known, so the first search is as fast as the next")

    def validate(self) -> "SearchSection":
        """Refuses values the search cannot use (one line naming the key)."""
        if not self.ray_cosine_resolution >= 0.0:         # NaN too
            raise ConfigError(f"search.ray_cosine_resolution={self.ray_cosine_resolution}: must be >= 0 "
                              "(0 = every deviation from the median counts)")
        if self.ray_evidence not in RAY_EVIDENCE:
            raise ConfigError(f"search.ray_evidence={self.ray_evidence!r}: must be one of {', '.join(RAY_EVIDENCE)}")
        if self.distinct_phrases < 0:
            raise ConfigError(f"search.distinct_phrases={self.distinct_phrases}: must be >= 0 (0 = every other phrase)")
        if not 0.0 < self.identity_threshold < 1.0:
            raise ConfigError(f"search.identity_threshold={self.identity_threshold}: must be a probability in (0, 1)")
        if self.instance_grace < 0:
            raise ConfigError(f"search.instance_grace={self.instance_grace}: must be >= 0 (map updates)")
        for k in ("fleet_footprint_m", "fleet_unreachable_tol_m"):
            if not getattr(self, k) >= 0.0:
                raise ConfigError(f"search.{k}={getattr(self, k)}: must be >= 0 (metres)")
        for k in ("fleet_unreachable_max", "fleet_unreachable_ttl_s"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"search.{k}={getattr(self, k)}: must be > 0")
        self.check_limits("search")
        return self
