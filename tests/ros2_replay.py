"""An independent ROS 2-over-Zenoh publisher for the tests: replays a ROS 2 bag's raw CDR
messages (serialised by rosbags' writer) on real Zenoh, as rmw_zenoh or
zenoh-bridge-ros2dds would, from its own process.

It imports nothing of ours: keys, graph tokens and attachments are written here by hand
from rmw_zenoh's documented layout, so the edge's decoder is checked against an outside
encoding, not against our own.

    python tests/ros2_replay.py BAG --listen tcp/127.0.0.1:PORT --layout rmw_zenoh \
        [--domain 0] [--distro humble|jazzy] [--speed 20] [--wait-subs 1] [--linger 2]

The session runs in router mode (like rmw_zenohd plus the node). It declares one
publisher per topic and, for rmw_zenoh, a node token and one publisher token per topic;
waits until ``--wait-subs`` of the topics have a matching subscriber (so no message is
lost before the edge subscribed); then sends every message in bag order, sleeping the
bag-time difference / ``--speed`` (messages with equal bag times go out back to back: a
burst). ``--latch TOPIC`` publishes that topic at once, before any subscriber, from an
advanced publisher with a cache (transient local, as robot_state_publisher's /tf_static).
Prints "READY" when its publishers are declared and "DONE <n>" at the end.
"""
from __future__ import annotations

import argparse
import json
import struct
import sys
import time

import zenoh
import zenoh.ext
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore


def dds_name(msgtype: str) -> str:
    pkg, sub, name = msgtype.split("/")
    return f"{pkg}::{sub}::dds_::{name}_"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("bag")
    ap.add_argument("--listen", required=True)
    ap.add_argument("--layout", choices=["rmw_zenoh", "bridge"], default="rmw_zenoh")
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--distro", choices=["humble", "jazzy"], default="humble")
    ap.add_argument("--speed", type=float, default=20.0)
    ap.add_argument("--wait-subs", type=int, default=1)
    ap.add_argument("--wait-s", type=float, default=60.0)
    ap.add_argument("--linger", type=float, default=2.0)
    ap.add_argument("--latch", action="append", default=[],
                    help="topic published at once, before any subscriber, from a cache (transient local)")
    a = ap.parse_args()

    store = get_typestore(Stores.ROS2_JAZZY if a.distro == "jazzy" else Stores.ROS2_HUMBLE)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([a.listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(conf)
    zid = str(s.zid())
    pubs, tokens = {}, []
    with AnyReader([__import__("pathlib").Path(a.bag)], default_typestore=store) as reader:
        conns = list(reader.connections)
        if a.layout == "rmw_zenoh":
            tokens.append(s.liveliness().declare_token(f"@ros2_lv/{a.domain}/{zid}/0/0/NN/%/%/replay"))
        for i, c in enumerate(conns):
            name = c.topic.lstrip("/")
            h = store.hash_rihs01(c.msgtype) if a.distro == "jazzy" else "TypeHashNotSupported"
            key = f"{a.domain}/{name}/{dds_name(c.msgtype)}/{h}" if a.layout == "rmw_zenoh" else name
            if c.topic in a.latch:  # like rmw_zenoh's transient-local publishers: a cache late joiners query
                pub = zenoh.ext.declare_advanced_publisher(s, key, cache=zenoh.ext.CacheConfig(max_samples=10),
                                                           publisher_detection=True)
            else:
                pub = s.declare_publisher(key)
            pubs[c.id] = (pub, c.topic)
            if a.layout == "rmw_zenoh":
                tokens.append(s.liveliness().declare_token(
                    f"@ros2_lv/{a.domain}/{zid}/0/{i + 1}/MP/%/%/replay/{c.topic.replace('/', '%')}/"
                    f"{dds_name(c.msgtype)}/{h}/::,:,:,:,,"))
        gid = bytes(range(16))
        n = 0
        latched = [c for c in conns if c.topic in a.latch]
        for conn, _ns, raw in (reader.messages(connections=latched) if latched else ()):  # [] would mean all
            pubs[conn.id][0].put(bytes(raw))
            n += 1
        print("READY", flush=True)
        end = time.monotonic() + a.wait_s
        while time.monotonic() < end:
            if sum(p.matching_status.matching for p, t in pubs.values() if t not in a.latch) >= a.wait_subs:
                break
            time.sleep(0.05)
        else:
            print("no subscriber matched", file=sys.stderr, flush=True)
        time.sleep(0.3)
        t_prev = None
        for conn, ns, raw in reader.messages(connections=[c for c in conns if c.topic not in a.latch]):
            if t_prev is not None and a.speed > 0:
                time.sleep(max(0.0, (ns - t_prev) * 1e-9 / a.speed))
            t_prev = ns
            pub, _ = pubs[conn.id]
            att = struct.pack("<qqB", n + 1, time.time_ns(), 16) + gid
            pub.put(bytes(raw), attachment=att if a.layout == "rmw_zenoh" else None)
            n += 1
    print(f"DONE {n}", flush=True)
    time.sleep(a.linger)
    for t in tokens:
        t.undeclare()
    for p, _ in pubs.values():
        p.undeclare()
    s.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
