"""Probe: seed 0, synthetic, ground, 20 m, landmark 'water tower', rayfronts policy,
--pca-fit vocabulary --background vocabulary [--ray-evidence distinct|margin].
Runs apps.closed_loop.episode.run_episode with a recording LocalMapper (built exactly as
run_episode builds it), a recording decide() and a recording chain.render; first N steps.
Writes OUTDIR/steps.csv (per step), OUTDIR/goals.jsonl (all look-next goals per step).
Findings: docs/results/closed_loop_robot.md ("The town's tower, step by step").

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/diagnostics/town_tower_rays.py --steps 60 --out /tmp/rays
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root

import apps.closed_loop.episode as episode_mod
import apps.closed_loop.policies as pol
from apps.closed_loop.episode import run_episode
from apps.closed_loop.evaluate import SearchEvalConfig, make_world, seed_missions
from apps.closed_loop.policies import MIN_RAY_Z, POLICIES
from apps.closed_loop.policies import decide as real_decide
from apps.closed_loop.robot import Platform
from apps.closed_loop.sensing import EdgeChain
from apps.closed_loop.world_model import LocalMapper

ap = argparse.ArgumentParser()
ap.add_argument("--steps", type=int, default=60)
ap.add_argument("--ray-evidence", default="distinct")
ap.add_argument("--out", default="town_tower_rays")
ap.add_argument("--angle-bin", type=float, default=None, help="ray angle bin (deg; default: the loop's)")
a = ap.parse_args()
out = Path(a.out)
out.mkdir(parents=True, exist_ok=True)

T0 = time.perf_counter()
cfg = SearchEvalConfig(platform="ground", depth_limits=[20.0], seeds=[0], episodes=1, policies=["rayfronts"],
                       missions=["landmark"], background="vocabulary", world="synthetic", sensor="realistic",
                       encoder="sim", pca_fit="vocabulary", ray_evidence=a.ray_evidence,
                       angle_bin_deg=a.angle_bin).validate()
robot = Platform.make(cfg.platform)
world = make_world(cfg.world, 0)
missions = seed_missions(cfg, world, robot, 0)
kind, e, mission = missions[0]
assert kind == "landmark" and mission.target == "water tower", (kind, mission.target)
full_budget = mission.budget_steps
chain = EdgeChain(world, cfg.sensor_config(0), fit_at=missions[0][2].start)
settings = dataclasses.replace(cfg.loop_settings(), depth_limit_m=20.0)
print(f"setup {time.perf_counter() - T0:.1f}s; start {mission.start}, shortest {mission.shortest_m:.1f} m, "
      f"budget {full_budget}; capped at {a.steps}", flush=True)

def insts(name):
    return [(i.id, (np.asarray(i.aabb_min, float) + np.asarray(i.aabb_max, float)) / 2, np.asarray(i.aabb_min, float),
             np.asarray(i.aabb_max, float)) for i in world.instances if world.classes[i.class_id] == name]

WT, RT = insts("water tower"), insts("radio tower")
print("water tower", [(i, c.round(1).tolist(), lo[2], hi[2]) for i, c, lo, hi in WT])
print("radio tower", [(i, c.round(1).tolist(), lo[2], hi[2]) for i, c, lo, hi in RT], flush=True)

# --- the mapper, exactly as run_episode builds it ---
method, semantic, poses = POLICIES["rayfronts"]
mcfg = settings.map_config(method, world, chain.cfg.resolution)
print("angle bin", mcfg.map.angle_bin_size, "search cfg:", mcfg.search.ray_evidence,
      "distinct_phrases", mcfg.search.distinct_phrases, "n background", len(mcfg.search.background), flush=True)

records: list[dict] = []

def bearing_deg(frm, to):
    return math.degrees(math.atan2(to[1] - frm[1], to[0] - frm[0]))

def adiff(a1, a2):
    return abs((a1 - a2 + 180.0) % 360.0 - 180.0)

class RecordingMapper(LocalMapper):
    def observe(self, targets, at, *args, **kw):
        obs = super().observe(targets, at, *args, **kw)
        rec = {"at": np.asarray(at, float).copy(), "obs": obs}
        # per-ray evidence of this search (the _Scored entry answer_search just used)
        try:
            from mapper.search_answer import _SCORED, _in_area
            from planning.look_next import ray_outlier_z
            store = _SCORED.get(self.snap)
            sc = list(store.entries.values())[-1]
            rz = ray_outlier_z(sc.rcos, self.cfg.search.ray_cosine_resolution)[0]
            o = self.snap.ray_origins.astype(np.float64)
            d = self.snap.ray_dirs.astype(np.float64)
            zb = kw.get("z_band")
            keep = _in_area(o, None, zb)
            rec["rays"] = (o[keep], d[keep], rz[keep], np.asarray(sc.rs[0])[keep], np.asarray(sc.rcos[0])[keep])
            rec["feats"] = self.snap.ray_feats[:len(keep)].detach().cpu().float().numpy()[keep].astype(np.float16)
            allc = np.asarray(sc.rcos[0], np.float64)
            rec["all_rays"] = (len(allc), float(np.median(allc)), float(np.median(np.abs(allc - np.median(allc)))))
        except Exception as ex:  # noqa: BLE001
            rec["rays_err"] = repr(ex)
        records.append(rec)
        return obs

mapper = RecordingMapper(chain.space, mcfg, robot.costmap_band(settings.vox_m), settings.window_m, score_poses=poses)

# record decisions
decisions: list = []
def rec_decide(*args, **kw):
    d = real_decide(*args, **kw)
    decisions.append(d)
    return d
episode_mod.decide = rec_decide

# record which goals decide() could use: reachable (not set aside, progress), passed

elig: dict = {}
_rg, _pa = pol._reachable_goals, pol._passed
def rec_reachable(obs, nav, state):
    got = _rg(obs, nav, state)
    elig[len(records) - 1] = {"reachable": [dict(pos=[round(float(v), 2) for v in g["position"][:2]],
                                                 head=round(math.degrees(g["heading_rad"]), 1),
                                                 ray_z=round(float(g.get("ray_z", 0)), 3),
                                                 score=round(float(g.get("score", 0)), 4),
                                                 path_m=round(float(p), 2), gap_m=round(float(g.get("gap_m", 0)), 2))
                                            for g, _, p in got],
                              "n_look_next": len(obs.look_next), "set_aside": len(state.set_aside),
                              "bearing": None if state.bearing is None else
                              [round(math.degrees(state.bearing[0]), 1), round(state.bearing[1], 3)]}
    return got
def rec_passed(goals, at, *a2, **k2):
    got = _pa(goals, at, *a2, **k2)
    e = elig.get(len(records) - 1)
    if e is not None:
        e["passed"] = [[round(float(v), 2) for v in g["position"][:2]] for g, _, _ in got]
    return got
pol._reachable_goals, pol._passed = rec_reachable, rec_passed

# record tower pixels in each step's rendered views
pix: list = []
_render = chain.render
def rec_render(pose):
    r = _render(pose)
    pix.append({i: int((r.instance == i).sum()) for i, *_ in WT + RT})
    return r
chain.render = rec_render

step_t: list[float] = []
_orig_obs = mapper.observe
t_last = [time.perf_counter()]
def timed_observe(*args, **kw):
    o = _orig_obs(*args, **kw)
    now = time.perf_counter()
    step_t.append(now - t_last[0])
    t_last[0] = now
    print(f"step {len(records)-1}: {step_t[-1]:.1f}s since last, at {np.round(args[1][:2],1)}, "
          f"{len(o.look_next)} goals, top ray_z {max([g.get('ray_z',0) for g in o.look_next] or [0]):.2f}", flush=True)
    return o
mapper.observe = timed_observe

short = dataclasses.replace(mission, budget_steps=a.steps)
T1 = time.perf_counter()
row = run_episode(world, short, "rayfronts", settings, chain=chain, mapper=mapper)
T2 = time.perf_counter()
print(f"episode {T2 - T1:.1f}s for {row['steps']} steps; success {row['success']} path {row['path_m']:.1f} "
      f"end {np.round(row['end'],1)}", flush=True)

# ---- tables ----
views = chain.cfg.views
rows, gl = [], open(out / "goals.jsonl", "w")
for s, rec in enumerate(records):
    at, obs = rec["at"], rec["obs"]
    d = decisions[s] if s < len(decisions) else None
    wt = min(WT, key=lambda x: np.linalg.norm(x[1][:2] - at[:2]))
    rt = min(RT, key=lambda x: np.linalg.norm(x[1][:2] - at[:2]))
    wb, rb = bearing_deg(at, wt[1]), bearing_deg(at, rt[1])
    goals = []
    for g in obs.look_next:
        p = np.asarray(g["position"], float)
        h = math.degrees(g["heading_rad"])
        goals.append(dict(pos=p[:2].round(2).tolist(), head=round(h, 1), ray_z=round(float(g.get("ray_z", 0)), 3),
                          score=round(float(g.get("score", 0)), 4), gain=round(float(g.get("gain_m3", 0)), 1),
                          d_wt=round(adiff(h, bearing_deg(p, wt[1])), 1),
                          d_rt=round(adiff(h, bearing_deg(p, rt[1])), 1),
                          dist=round(float(np.linalg.norm(p[:2] - at[:2])), 1)))
    gl.write(json.dumps({"step": s, "at": at[:2].round(2).tolist(), "wt_bearing": round(wb, 1),
                         "rt_bearing": round(rb, 1), "goals": goals,
                         "decision": None if d is None else {"goal_xy": None if d.goal_xy is None else
                                                             np.asarray(d.goal_xy).round(2).tolist(), "why": d.why}})
             + "\n")
    zs = np.array([g["ray_z"] for g in goals]) if goals else np.zeros(0)
    ss = np.array([g["score"] for g in goals]) if goals else np.zeros(0)

    def rank_of(idx, v):
        return int((v > v[idx]).sum() + 1)

    def best(match_key, goals=goals, zs=zs, ss=ss):
        m = [i for i, g in enumerate(goals) if g[match_key] <= 20.0]
        if not m:
            return dict(n=0)
        iz = max(m, key=lambda i: (zs[i], ss[i]))
        i_s = max(m, key=lambda i: (ss[i], zs[i]))
        return dict(n=len(m), z=zs[iz], z_rank=rank_of(iz, zs), s=ss[i_s], s_rank=rank_of(i_s, ss),
                    z_head=goals[iz]["head"])
    bw, br = best("d_wt"), best("d_rt")
    top = int(np.argmax(zs)) if len(zs) else None
    tops = int(np.argmax(ss)) if len(ss) else None
    r = dict(step=s, x=round(at[0], 2), y=round(at[1], 2),
             wt_bearing=round(wb, 1), wt_dist=round(float(np.linalg.norm(wt[1][:2] - at[:2])), 1),
             rt_bearing=round(rb, 1), rt_dist=round(float(np.linalg.norm(rt[1][:2] - at[:2])), 1),
             n_goals=len(goals),
             wt_goals=bw["n"], wt_best_z=bw.get("z"), wt_z_rank=bw.get("z_rank"), wt_best_score=bw.get("s"),
             wt_score_rank=bw.get("s_rank"),
             rt_goals=br["n"], rt_best_z=br.get("z"), rt_z_rank=br.get("z_rank"), rt_best_score=br.get("s"),
             rt_score_rank=br.get("s_rank"),
             top_z=None if top is None else zs[top], top_z_head=None if top is None else goals[top]["head"],
             top_z_d_wt=None if top is None else goals[top]["d_wt"],
             top_z_d_rt=None if top is None else goals[top]["d_rt"],
             top_z_pos=None if top is None else goals[top]["pos"],
             top_score=None if tops is None else ss[tops], top_score_head=None if tops is None else goals[tops]["head"],
             n_goals_z_ge_3_5=int((zs >= MIN_RAY_Z).sum()),
             wt_px=sum(p[wt[0]] for p in pix[s * views:(s + 1) * views]) if len(pix) >= (s + 1) * views else None,
             rt_px=sum(p[rt[0]] for p in pix[s * views:(s + 1) * views]) if len(pix) >= (s + 1) * views else None,
             chosen=None if d is None or d.goal_xy is None else np.asarray(d.goal_xy).round(1).tolist(),
             chosen_bearing=(None if d is None or d.goal_xy is None
                             else round(bearing_deg(at, np.asarray(d.goal_xy)), 1)),
             why=None if d is None else d.why)
    # every ray of the map (in the z band): the water tower's and radio tower's best
    if "rays" in rec:
        o, dv, rz, rs, rc = rec["rays"]
        n = len(rz)
        hd = np.degrees(np.arctan2(dv[:, 1], dv[:, 0]))
        el = np.degrees(np.arctan2(dv[:, 2], np.hypot(dv[:, 0], dv[:, 1])))
        r["n_rays"] = n
        r["n_rays_z_ge_3_5"] = int((rz >= MIN_RAY_Z).sum())
        for tag, (_iid, c, lo, hi) in (("wt", wt), ("rt", rt)):
            b = np.degrees(np.arctan2(c[1] - o[:, 1], c[0] - o[:, 0]))
            dh = np.abs((hd - b + 180) % 360 - 180)
            hor = np.hypot(c[0] - o[:, 0], c[1] - o[:, 1])
            elo = np.degrees(np.arctan2(lo[2] - o[:, 2], hor))
            ehi = np.degrees(np.arctan2(hi[2] - o[:, 2], hor))
            m = (dh <= 20.0)
            mv = m & (el >= elo - 15.0) & (el <= ehi + 15.0)      # also pointing at its height (±15°, half a bin)
            r[f"{tag}_rays"] = int(m.sum())
            r[f"{tag}_rays_el"] = int(mv.sum())
            if m.any():
                k = np.flatnonzero(m)[np.argmax(rz[m])]
                r[f"{tag}_ray_max_z"] = round(float(rz[k]), 2)
                r[f"{tag}_ray_rank"] = int((rz > rz[k]).sum() + 1)
                r[f"{tag}_ray_max_p"] = float(rs[m].max())
                r[f"{tag}_rays_z_ge_3_5"] = int((rz[m] >= MIN_RAY_Z).sum())
        # the ray bins the tower itself falls in (theta bin of the bearing, phi bins of its height span)
        import torch

        from semantic_map.ray_frontiers import angle_bins, bin_counts
        psi = float(mcfg.map.angle_bin_size)
        nt, npb = bin_counts(psi)
        tb, pb = (t.numpy() for t in angle_bins(torch.as_tensor(dv), psi))
        # ray_z is the modified z-score among ALL the map's rays (before the z band): their median / MAD
        r["n_rays_all"], r["rcos_median_all"], r["rcos_mad_all"] = rec["all_rays"]
        r["rcos_for_z_3_5"] = r["rcos_median_all"] + MIN_RAY_Z * r["rcos_mad_all"] / 0.6745
        for tag, (_iid, c, lo, hi) in (("wt", wt), ("rt", rt)):
            th = np.degrees(np.arctan2(c[1] - o[:, 1], c[0] - o[:, 0]))
            ttb = np.remainder(np.round(th / (360.0 / nt)).astype(int), nt)
            hor = np.hypot(c[0] - o[:, 0], c[1] - o[:, 1])
            ph_top = np.degrees(np.arctan2(hor, hi[2] - o[:, 2]))     # polar angle from +z
            ph_bot = np.degrees(np.arctan2(hor, lo[2] - o[:, 2]))
            pb_top = np.clip(np.floor(ph_top / (180.0 / npb)), 0, npb - 1)
            pb_bot = np.clip(np.floor(ph_bot / (180.0 / npb)), 0, npb - 1)
            m = (tb == ttb) & (pb >= pb_top) & (pb <= pb_bot)
            r[f"{tag}_bin_rays"] = int(m.sum())
            if m.any():
                k = np.flatnonzero(m)[np.argmax(rz[m])]
                r[f"{tag}_bin_max_z"] = round(float(rz[k]), 2)
                r[f"{tag}_bin_rank"] = int((rz > rz[k]).sum() + 1)
                r[f"{tag}_bin_max_rcos"] = round(float(rc[m].max()), 4)
                r[f"{tag}_bin_max_p"] = float(rs[m].max())
                r[f"{tag}_bin_z_ge_3_5"] = int((rz[m] >= MIN_RAY_Z).sum())
            if tag == "wt":
                wt_mask = m
            else:
                rt_mask = m
        np.savez_compressed(out / f"rays_{s:03d}.npz", o=o.astype(np.float32), d=dv.astype(np.float32), z=rz,
                            p=rs, rcos=rc, wt=wt_mask, rt=rt_mask, f=rec.get("feats"))
        k = int(np.argmax(rz)) if n else None
        if k is not None:
            r["ray_top_z"] = round(float(rz[k]), 2)
            r["ray_top_head"] = round(float(hd[k]), 1)
            r["ray_top_el"] = round(float(el[k]), 1)
            r["ray_top_origin"] = o[k][:2].round(1).tolist()
            r["ray_top_d_wt"] = round(float(adiff(hd[k], bearing_deg(o[k], wt[1]))), 1)
            r["ray_top_d_rt"] = round(float(adiff(hd[k], bearing_deg(o[k], rt[1]))), 1)
            r["ray_top_in_wt_bin"] = bool(wt_mask[k])
            r["ray_top_in_rt_bin"] = bool(rt_mask[k])
        r["ray_max_p"] = float(rs.max()) if n else None
    else:
        r["rays_err"] = rec.get("rays_err")
    rows.append(r)
gl.close()
with open(out / "eligible.jsonl", "w") as f:
    for k in sorted(elig):
        f.write(json.dumps({"step": k, **elig[k]}) + "\n")
keys = list(dict.fromkeys(k for r in rows for k in r))
with open(out / "steps.csv", "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow({k: (round(v, 3) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})
json.dump({"row": {k: v for k, v in row.items() if k not in ("finds",)}, "wall_s": time.perf_counter() - T0,
           "episode_s": T2 - T1, "full_budget": full_budget, "step_s": step_t}, open(out / "run.json", "w"),
          indent=1, default=float)
print(f"wrote {out}/steps.csv; total {time.perf_counter() - T0:.1f}s")
