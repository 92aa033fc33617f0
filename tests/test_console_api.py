"""``rayfronts console``'s HTTP API against real processes: a mapper and an edge on the
synthetic world (seed 0) and the console process (tests/support/console.py). Answers are
compared with the same calls made directly with ``query_client.Client`` and with the real
``rayfronts search --json`` CLI on the same (frozen) map, and validated against the console's
own OpenAPI document; bad input (a 9 MiB upload with or without Content-Length included) gives
one-line 4xx JSON; event streams are capped per client and in total and end with the client; the
console refuses a non-loopback bind without a token or without TLS (unless --insecure-http)
and, with a token, answers 401 without it. The token in a real browser over HTTPS:
tests/test_console_browser.py."""
from __future__ import annotations

import json
import subprocess
import urllib.parse

import numpy as np
import pytest

from tests.support.console import EventStream, http, matches_openapi, multipart, post_json, raw_post
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, cli_cmd, proc_env, stop_all, wait_for, wait_log
from tests.support.roles import client

pytestmark = pytest.mark.timeout(300)


def _one_line_error(status: int, body, lo: int = 400, hi: int = 499) -> str:
    assert lo <= status <= hi, (status, body)
    assert isinstance(body, dict) and set(body) == {"error"}, body
    assert "\n" not in body["error"] and "Traceback" not in body["error"] and body["error"], body
    return body["error"]


def test_stream_delivers_updates_and_cancels_on_disconnect(console_world):
    w = console_world
    w.wait_mapped(4)
    s = EventStream("127.0.0.1", w.port, "/api/search/stream?q=vehicle")
    try:
        first = s.next()
        if w.edge.p.poll() is not None:       # the edge already finished: make the map change again
            w.more_frames()
        second = s.next()
    finally:
        s.close()
    keys = {"found", "look_next", "beyond", "events", "frames_mapped", "map_version", "timings_ms", "missing_shards"}
    assert set(first) == keys and set(second) == keys
    assert second["map_version"] > first["map_version"], (first["map_version"], second["map_version"])
    # the console cancels the standing search when the client goes away
    wait_for(lambda: http(w.url("/api/stats"))[1]["console"]["open_streams"] == 0, 20, what="stream closed")
    # a standing query: its update, then the mapper forgets it after the disconnect
    q = EventStream("127.0.0.1", w.port, "/api/query/stream?q=vehicle&top_k=3")
    try:
        upd = q.next()
        assert upd["query"] == "vehicle" and upd["frames_mapped"] > 0
        with client(w.ep) as c:
            assert len(c.stats()["standing_queries"]) == 1
    finally:
        q.close()
    with client(w.ep) as c:
        wait_for(lambda: c.stats()["standing_queries"] == [], 20, what="standing query cancelled")


def test_search_equals_the_cli(console_world):
    w = console_world
    w.wait_frozen()
    opts = ["--threshold", "0.6", "--from", "0,0,1", "--max-instances", "5"]
    cli = subprocess.run(cli_cmd("search", "vehicle", "--json", *opts, "--connect", w.ep, "--timeout", "60"),
                         env=proc_env(), cwd=str(ROOT), capture_output=True, text=True, timeout=120)
    assert cli.returncode == 0, cli.stderr[-2000:]
    want = json.loads(cli.stdout)
    st, got = http(w.url("/api/search?q=vehicle&threshold=0.6&from=0,0,1&max_instances=5"))
    assert st == 200, got
    st, posted = post_json(w.url("/api/search"), {"q": ["vehicle"], "threshold": 0.6, "from": [0, 0, 1],
                                                  "max_instances": 5})
    assert st == 200, posted
    assert want["found"], "the synthetic world's vehicles are found"
    for g in (got, posted):
        assert set(g) == set(want)
        assert g["map_version"] == want["map_version"] and g["frames_mapped"] == want["frames_mapped"]
        assert [(f["id"], f["target"]) for f in g["found"]] == [(f["id"], f["target"]) for f in want["found"]]
        assert g["events"] == want["events"]          # what this map version changed, for every search of it
        assert np.allclose([f["confidence"] for f in g["found"]], [f["confidence"] for f in want["found"]])
        assert len(g["look_next"]) == len(want["look_next"])
        assert [sorted(x) for x in g["look_next"]] == [sorted(x) for x in want["look_next"]]
        assert sorted(g["beyond"]) == sorted(want["beyond"])
    # two targets and an area far away: nothing found there
    st, far = http(w.url("/api/search?q=vehicle&q=car&area=1000,1000,1010,1010&z_band=0,3"))
    assert st == 200 and far["found"] == [] and far["look_next"] == []


def _car_png(world) -> bytes:
    import cv2

    res = (240, 320)
    pose = world.trajectory("ground", 40)[20]
    r = world.render(pose, world.camera(res, 90.0), res)
    cid = world.class_id("car")
    ys, xs = np.nonzero(r.labels == cid)
    assert len(ys), "a car in view"
    crop = r.rgb[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(crop[..., ::-1]))
    assert ok
    return buf.tobytes()


def test_every_endpoint_matches_the_client(console_world):
    from synthetic_world import World

    w = console_world
    w.wait_frozen()
    with client(w.ep) as c:
        # queries: GET, POST JSON, POST image upload
        direct = c.query("vehicle", top_k=3)
        st, got = http(w.url("/api/query?q=vehicle&top_k=3"))
        assert st == 200 and np.allclose(got["cluster_xyz"], direct.cluster_xyz), got
        st, posted = post_json(w.url("/api/query"), {"q": "vehicle", "top_k": 3})
        assert st == 200 and np.allclose(posted["cluster_score"], direct.cluster_score)
        png = _car_png(World.generate(0))
        body, ctype = multipart({"image": ("car.png", png, "image/png"), "top_k": "3"})
        st, img = http(w.url("/api/query"), data=body, headers={"Content-Type": ctype}, method="POST")
        want = c.query(image=png, top_k=3)
        assert st == 200 and img["query"] == "<image>", img
        assert np.allclose(img["cluster_xyz"], want.cluster_xyz) and len(want.cluster_xyz)
        # occupancy
        st, box = http(w.url("/api/occupancy/box?min=-5,-5,0&max=5,5,3&stride=1"))
        assert st == 200 and np.array_equal(box["states"], c.occupancy_box([-5, -5, 0], [5, 5, 3]).states)
        st, sl = http(w.url("/api/occupancy/slice?min=-5,-5&max=5,5&z_band=0,3"))
        assert st == 200 and np.array_equal(sl["states"], c.occupancy_slice([-5, -5], [5, 5], [0, 3]).states)
        pts = [[0.0, 0.0, 1.0], [3.0, 2.0, 0.5]]
        st, op = post_json(w.url("/api/occupancy/points"), {"points": pts, "radius": 2.0})
        dp = c.occupancy_points(pts, radius=2.0)
        assert st == 200 and op["states"] == dp.states.tolist()
        assert np.allclose([np.inf if v is None else v for v in op["dist"]], dp.dist)
        # stats per shard and robot
        st, stats = http(w.url("/api/stats"))
        truth = c.stats()
        assert st == 200 and list(stats["shards"]) == [""]
        r1 = stats["shards"][""]["robots"]["r1"]
        assert r1["mapped"] == truth["robots"]["r1"]["mapped"] and r1["dropped"] == truth["robots"]["r1"]["dropped"]
        assert r1["last_seen"] and r1["last_seen_s_ago"] >= 0 and "edge_status" in r1 and "rate_hz" in r1
        # snapshots: make one, then it is the one described
        st, made = http(w.url("/api/snapshot"), method="POST", data=b"")
        assert st == 200, made
        st, desc = http(w.url("/api/snapshot"))
        assert st == 200 and desc == c.snapshot()


def test_openapi_and_pages_are_complete_and_local(console_world):
    from openapi_spec_validator import validate

    w = console_world
    w.wait_frozen()
    st, spec = http(w.url("/openapi.json"))
    assert st == 200
    validate(spec)
    # security: a bearer scheme (and the page's cookie); the JSON and the image bodies of POST /api/query
    assert spec["components"]["securitySchemes"]["bearer"] == {"type": "http", "scheme": "bearer",
                                                               "description": "Authorization: Bearer TOKEN"}
    assert {"bearer": []} in spec["security"]
    body = spec["paths"]["/api/query"]["post"]["requestBody"]["content"]
    assert body["application/json"]["schema"]["required"] == ["q"]
    assert set(body["application/json"]["schema"]["properties"]) == {"q", "top_k", "softmax"}
    assert body["multipart/form-data"]["schema"]["properties"]["image"]["format"] == "binary"
    # every route's reply is typed, and what the console answers is what the document says
    for p, ops in spec["paths"].items():
        for m, op in ops.items():
            assert "$ref" in op["responses"]["200"]["content"]["application/json"]["schema"], (m, p)
    gets = ["/api/config", "/api/search?q=vehicle", "/api/query?q=vehicle&top_k=3", "/api/stats", "/api/snapshot",
            "/api/occupancy/box?min=-3,-3,0&max=3,3,2", "/api/occupancy/slice?min=-3,-3&max=3,3&z_band=0,2"]
    for url in gets:
        st, reply = http(w.url(url))
        assert st == 200, (url, reply)
        matches_openapi(spec, url.split("?")[0], "get", reply)
    st, found = http(w.url("/api/search?q=vehicle"))
    assert found["found"] and found["look_next"], "something to check: instances and goals"
    for path, obj in (("/api/query", {"q": "vehicle", "top_k": 2}), ("/api/search", {"q": ["vehicle"]}),
                      ("/api/occupancy/points", {"points": [[0, 0, 1]], "radius": 2.0})):
        st, reply = post_json(w.url(path), obj)
        assert st == 200, (path, reply)
        matches_openapi(spec, path, "post", reply)
    st, err = http(w.url("/api/search?q=vehicle&threshold=2"))
    matches_openapi(spec, "/api/search", "get", err, st)
    s = EventStream("127.0.0.1", w.port, "/api/search/stream?q=vehicle")
    try:
        matches_openapi(spec, "/api/search/stream", "get", s.next())
    finally:
        s.close()
    want = {("get", "/api/query"), ("post", "/api/query"), ("get", "/api/search"), ("post", "/api/search"),
            ("get", "/api/search/stream"), ("get", "/api/query/stream"), ("get", "/api/occupancy/box"),
            ("get", "/api/occupancy/slice"), ("post", "/api/occupancy/points"), ("get", "/api/stats"),
            ("get", "/api/snapshot"), ("post", "/api/snapshot"), ("get", "/api/config")}
    have = {(m, p) for p, ops in spec["paths"].items() for m in ops}
    assert want <= have, want - have
    for path in ("/", "/docs", "/static/console.js"):
        st, page = http(w.url(path))
        assert st == 200 and isinstance(page, str) and page
        assert "https://" not in page and "http://" not in page.replace("http://127.0.0.1", ""), path


def test_bad_inputs_one_line_4xx(console_world):
    w = console_world
    cases = [
        ("/api/query", None, "q"),
        ("/api/query?q=%20", None, "empty"),
        ("/api/query?q=car&top_k=0", None, "top_k"),
        ("/api/search?q=vehicle&threshold=1.5", None, "threshold"),
        ("/api/search?q=vehicle&from=1,2", None, "--from"),
        ("/api/search?q=vehicle&area=1,2,3", None, "--area"),
        ("/api/search?q=vehicle&z_band=3,1", None, "z0 <= z1"),
        ("/api/occupancy/box?min=a,b,c&max=1,1,1", None, "min"),
        ("/api/occupancy/box?min=-2000,-2000,0&max=2000,2000,10", None, "limit"),
        ("/api/nowhere", None, "Not Found"),
    ]
    for path, _, needle in cases:
        st, body = http(w.url(path.replace(" ", "%20")))
        assert needle.lower() in _one_line_error(st, body).lower(), (path, body)
    posts = [
        ("/api/query", b"{not json", "application/json", "JSON"),
        ("/api/search", b'{"q": "vehicle", "threshold": "x"}', "application/json", "threshold"),
        ("/api/occupancy/points", b'{"points": [[1, 2]]}', "application/json", "points"),
    ]
    for path, data, ctype, needle in posts:
        st, body = http(w.url(path), data=data, headers={"Content-Type": ctype}, method="POST")
        assert needle.lower() in _one_line_error(st, body).lower(), (path, body)
    body, ctype = multipart({"image": ("x.png", b"not an image at all", "image/png")})
    st, err = http(w.url("/api/query"), data=body, headers={"Content-Type": ctype}, method="POST")
    assert "image" in _one_line_error(st, err)
    refused = http(w.url("/api/stats"))[1]["console"]["refused"]["body_too_large"]
    # a 9 MiB upload is refused from its Content-Length, before the body is read
    st, err = raw_post("127.0.0.1", w.port, "/api/query", {"Content-Type": "image/png",
                                                            "Content-Length": str(9 << 20)}, [b"\0" * 4096])
    assert "too large (limit 8 MiB)" in _one_line_error(st, err) and st == 413
    # and chunked (no Content-Length): refused once the chunks pass 8 MiB
    body, ctype = multipart({"image": ("big.png", b"\0" * (9 << 20), "image/png")})
    st, err = raw_post("127.0.0.1", w.port, "/api/query", {"Content-Type": ctype},
                       [body[i:i + (1 << 20)] for i in range(0, len(body), 1 << 20)])
    assert "too large (limit 8 MiB)" in _one_line_error(st, err) and st == 413
    # a chunked body under the cap is read whole and answered
    st, ok = raw_post("127.0.0.1", w.port, "/api/query", {"Content-Type": "application/json"},
                      [b'{"q": "vehi', b'cle", "top_k": 2}'])
    assert st == 200 and ok["query"] == "vehicle", ok
    assert http(w.url("/api/config"))[0] == 200          # still serving
    assert http(w.url("/api/stats"))[1]["console"]["refused"]["body_too_large"] == refused + 2   # counted


def test_non_loopback_needs_a_token(console_world, tmp_path):
    w = console_world
    port = free_port()
    r = subprocess.run(cli_cmd("console", "--connect", w.ep, "--http", f"0.0.0.0:{port}"), env=proc_env(),
                       cwd=str(ROOT), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--token" in r.stderr, r.stderr
    # a token but no TLS: refused too, naming both ways out
    r = subprocess.run(cli_cmd("console", "--connect", w.ep, "--http", f"0.0.0.0:{port}", "--token", "s3cret"),
                       env=proc_env(), cwd=str(ROOT), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--tls-cert PEM --tls-key PEM" in r.stderr and "--insecure-http" in r.stderr, r.stderr
    # with a token, plain HTTP asked for explicitly (and a key space no mapper serves: 503), every interface
    p = Proc("console-token", ["console", "--connect", w.ep, "--http", f"0.0.0.0:{port}", "--token", "s3cret",
                               "--insecure-http", "--rate-limit", "6", "--prefix", "nobody", "--timeout", "5"],
             tmp_path)
    try:
        wait_log(p.p, tmp_path / "console-token.log", "console at", 60)
        base = f"http://127.0.0.1:{port}"
        wait_for(lambda: http(base + "/api/config", timeout=5)[0] == 401, 30, what="console serving")
        st, body = http(base + "/api/config")
        assert "?token=TOKEN" in _one_line_error(st, body) and "Bearer TOKEN" in body["error"] and st == 401
        st, body = http(base + "/api/config", headers={"Authorization": "Bearer wrong"})
        assert st == 401
        assert http(base + "/api/config", headers={"Authorization": "Bearer s3cret"}) == (200, {"viewer_url": None})
        assert http(base + "/api/config?" + urllib.parse.urlencode({"token": "s3cret"}))[0] == 200
        st, body = http(base + "/api/stats?token=s3cret")
        assert st == 503 and "no mapper answered" in body["error"] and "\n" not in body["error"], body
        codes = [http(base + "/api/config?token=s3cret")[0] for _ in range(4)]
        assert codes[-1] == 429 and 200 in codes, codes
    finally:
        stop_all([p])


def test_event_streams_are_capped_and_end_with_the_client(console_world, tmp_path):
    """2 streams per client address, 3 in all: the third from one address and the fourth in all
    are refused (one line, naming the option), nothing starts on the mapper for them; a closed
    stream frees its slot and its standing query."""
    w = console_world
    w.wait_mapped(4)
    port = free_port()
    p = Proc("console-caps", ["console", "--connect", w.ep, "--http", f"127.0.0.1:{port}", "--timeout", "60",
                              "--max-streams", "3", "--max-streams-per-client", "2"], tmp_path)
    path = "/api/query/stream?q=vehicle&top_k=2"
    opened: list[EventStream] = []
    try:
        wait_log(p.p, tmp_path / "console-caps.log", "console at", 120)
        base = f"http://127.0.0.1:{port}"

        def stream(source: str) -> EventStream:
            s = EventStream("127.0.0.1", port, path, source=source)
            opened.append(s)
            return s

        with client(w.ep) as c:
            def standing() -> int:
                return len(c.stats()["standing_queries"])

            wait_for(lambda: standing() == 0, 30, what="no standing query left by other tests")
            a1, a2 = stream("127.0.0.1"), stream("127.0.0.1")
            assert a1.status == a2.status == 200 and a1.next()["query"] == "vehicle"
            a3 = stream("127.0.0.1")
            assert a3.status == 429 and "--max-streams-per-client" in _one_line_error(429, a3.error())
            b1 = stream("127.0.0.2")
            assert b1.status == 200 and b1.next()["query"] == "vehicle"
            c1 = stream("127.0.0.3")
            assert c1.status == 503
            assert "limit 3 in total" in _one_line_error(503, c1.error(), 503, 503)
            assert http(base + "/api/stats")[1]["console"]["open_streams"] == 3
            wait_for(lambda: standing() == 3, 20, what="3 standing queries (none for the refused streams)")
            a1.close()
            wait_for(lambda: http(base + "/api/stats")[1]["console"]["open_streams"] == 2, 20, what="slot freed")
            wait_for(lambda: standing() == 2, 20, what="the closed stream's standing query cancelled")
            c2 = stream("127.0.0.3")
            assert c2.status == 200 and c2.next()["query"] == "vehicle"
            for s in opened:
                s.close()
            wait_for(lambda: http(base + "/api/stats")[1]["console"]["open_streams"] == 0, 20, what="all closed")
            wait_for(lambda: standing() == 0, 20, what="every standing query cancelled")
            assert http(base + "/api/stats")[1]["console"]["refused"] == {"token": 0, "rate": 0, "body_too_large": 0,
                                                                          "streams": 2}
    finally:
        for s in opened:
            s.close()
        stop_all([p])
