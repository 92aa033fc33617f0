"""Test helper (no tests here): a Zenoh process driven line by line over stdin/stdout.

As a child (``python tests/support/zenoh_agent.py '<ZenohConfig as JSON>'``) it opens a real
Zenoh session with :mod:`common.zenoh_session` and executes JSON commands read from stdin,
answering one JSON line per command on stdout. As a module it provides :class:`Agent`, the
parent-side handle the network tests use, and :class:`Router`; the ``closer`` fixture
(tests/conftest.py) closes them all.

Commands: ``sub``/``lsub`` (declare a (liveliness) subscriber recording what arrives),
``put``, ``queryable`` (reply with a fixed payload), ``get``/``lget`` (query, liveliness
query), ``token`` / ``untoken``, ``received`` (what a subscriber got, optionally waiting for
``n`` samples up to ``timeout`` s), ``info``, ``close``. Every wait is bounded.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- child side
class _Child:
    """The child's session and what its commands declared; one method per command."""

    def __init__(self, guard, out):
        self.guard, self.s, self.out = guard, guard.session, out
        self.got: dict[str, list] = {}
        self.cond = threading.Condition()
        self.tokens: dict[str, object] = {}

    def say(self, obj) -> None:
        self.out.write(json.dumps(obj) + "\n")
        self.out.flush()

    def recorder(self, name):
        def cb(sample):
            with self.cond:
                self.got[name].append({"key": str(sample.key_expr), "kind": str(sample.kind),
                                       "payload": sample.payload.to_string()})
                self.cond.notify_all()
        return cb

    def op_sub(self, c):
        self.got[c["name"]] = []
        self.guard.add(self.s.declare_subscriber(c["key"], self.recorder(c["name"])))
        self.say({"ok": True})

    def op_lsub(self, c):
        self.got[c["name"]] = []
        self.guard.add(self.s.liveliness().declare_subscriber(c["key"], self.recorder(c["name"]),
                                                              history=c.get("history", True)))
        self.say({"ok": True})

    def op_put(self, c):
        self.s.put(c["key"], c.get("payload", "x").encode())
        self.say({"ok": True})

    def op_queryable(self, c):
        payload = c.get("reply", "reply")

        def on_query(q, payload=payload):
            with q:
                q.reply(q.key_expr, payload.encode())
        self.guard.add(self.s.declare_queryable(c["key"], on_query))
        self.say({"ok": True})

    def op_get(self, c, liveliness: bool = False):
        src = self.s.liveliness() if liveliness else self.s
        kw = {"timeout": float(c.get("timeout", 3.0))}
        if not liveliness:
            kw["payload"] = c.get("payload", "")
        res = []
        for r in src.get(c["key"], **kw):
            if r.ok is not None:
                res.append({"key": str(r.ok.key_expr), "payload": r.ok.payload.to_string()})
            else:
                res.append({"err": r.err.payload.to_string()})
        self.say({"ok": True, "replies": res})

    def op_lget(self, c):
        self.op_get(c, liveliness=True)

    def op_token(self, c):
        self.tokens[c["key"]] = self.guard.add(self.s.liveliness().declare_token(c["key"]))
        self.say({"ok": True})

    def op_untoken(self, c):
        self.tokens.pop(c["key"]).undeclare()
        self.say({"ok": True})

    def op_received(self, c):
        n, deadline = int(c.get("n", 0)), time.monotonic() + float(c.get("timeout", 0.0))
        with self.cond:
            while len(self.got[c["name"]]) < n and time.monotonic() < deadline:
                self.cond.wait(max(deadline - time.monotonic(), 0.0))
            self.say({"ok": True, "samples": list(self.got[c["name"]])})

    def op_info(self, c):
        self.say({"ok": True, "routers": [str(z) for z in self.s.info.routers_zid()],
                  "peers": [str(z) for z in self.s.info.peers_zid()]})

    def serve(self, lines) -> None:
        """Execute one JSON command per line until ``close`` or the end of ``lines``."""
        for line in lines:
            line = line.strip()
            if not line:
                continue
            c = json.loads(line)
            op = c["op"]
            if op == "close":
                break
            handler = getattr(self, f"op_{op}", None)
            try:
                if handler is None:
                    self.say({"ok": False, "error": f"unknown op {op}"})
                else:
                    handler(c)
            except Exception as e:
                self.say({"ok": False, "error": f"{type(e).__name__}: {e}"})


def _child(spec: dict) -> int:
    sys.path.insert(0, str(ROOT))

    from common.zenoh_session import SessionGuard, ZenohConfig, open_session

    opts = spec.pop("_open", {})
    cfg = ZenohConfig(**spec)
    out = sys.stdout
    try:
        guard = SessionGuard(open_session(cfg, default_mode=opts.get("default_mode", "client")))
    except Exception as e:
        out.write(json.dumps({"ok": False, "error": f"{type(e).__name__}: {e}"}) + "\n")
        out.flush()
        return 3
    child = _Child(guard, out)
    child.say({"ok": True, "zid": str(guard.session.zid())})
    try:
        child.serve(sys.stdin)
    finally:
        guard.close()
    child.say({"ok": True, "closed": True})
    return 0


# --------------------------------------------------------------------------- parent side
class AgentError(RuntimeError):
    pass


PROBE = "__probe__"


class Agent:
    """A child process holding one Zenoh session; call :meth:`cmd` to drive it."""

    def __init__(self, name: str = "agent", timeout: float = 20.0, default_mode: str = "client",
                 wait: bool = True, argv_prefix: tuple[str, ...] = (), **cfg):
        """Start the child; with ``wait`` (default) block until its session is open (or failed)."""
        self.name = name
        self.timeout = timeout
        spec = dict(cfg)
        spec.setdefault("multicast_scouting", False)
        spec.setdefault("shared_memory", False)
        spec["_open"] = {"default_mode": default_mode}
        env = dict(os.environ, PYTHONPATH=str(ROOT), RUST_LOG=os.environ.get("RUST_LOG", "error"))
        self.proc = subprocess.Popen([*argv_prefix, sys.executable, __file__, json.dumps(spec)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                     cwd=str(ROOT))
        self._lines: list[str] = []
        self._cv = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.hello: dict = {}
        if wait:
            self.wait_ready(timeout)

    def wait_ready(self, timeout: float) -> dict:
        """Wait for the child's first line (session open or failed) and return it."""
        if not self.hello:
            self.hello = self._next(timeout)
        return self.hello

    def _read(self):
        for line in self.proc.stdout:
            with self._cv:
                self._lines.append(line)
                self._cv.notify_all()
        with self._cv:
            self._lines.append("")  # EOF marker
            self._cv.notify_all()

    def _next(self, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        with self._cv:
            while not self._lines:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AgentError(f"{self.name}: no answer within {timeout} s")
                self._cv.wait(left)
            line = self._lines.pop(0)
        if not line:
            err = self.proc.stderr.read() if self.proc.poll() is not None else ""
            raise AgentError(f"{self.name}: process ended (rc={self.proc.poll()}): {err[-2000:]}")
        return json.loads(line)

    @property
    def connected(self) -> bool:
        return bool(self.hello.get("ok"))

    def cmd(self, op: str, _wait: float | None = None, **kw) -> dict:
        """Send command ``op`` with fields ``kw``; wait at most ``_wait`` s for the answer."""
        if not self.connected:
            raise AgentError(f"{self.name}: not connected: {self.hello}")
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        r = self._next(_wait or self.timeout)
        if not r.get("ok"):
            raise AgentError(f"{self.name}: {op} failed: {r}")
        return r

    def received(self, name: str, n: int = 0, timeout: float = 0.0, probes: bool = False) -> list[dict]:
        """Samples subscriber ``name`` got (probe samples of :func:`await_route` left out unless
        ``probes``), waiting up to ``timeout`` s for at least ``n`` of them."""
        deadline = time.monotonic() + timeout
        while True:
            left = max(deadline - time.monotonic(), 0.0)
            got = self.cmd("received", _wait=left + self.timeout, name=name, n=0, timeout=0.0)["samples"]
            if not probes:
                got = [x for x in got if not x["payload"].startswith(PROBE)]
            if len(got) >= n or left <= 0:
                return got
            time.sleep(min(0.05, left))

    def kill(self) -> None:
        """SIGKILL the child (no clean close: the peers must notice through Zenoh)."""
        self.proc.kill()
        self.proc.wait(timeout=10)

    def close(self) -> int:
        """Close the session and wait for the process (kills it after a bounded wait)."""
        if self.proc.poll() is None:
            try:
                if self.connected:
                    self.proc.stdin.write(json.dumps({"op": "close"}) + "\n")
                    self.proc.stdin.flush()
                    self.proc.stdin.close()
                else:  # still connecting (or failed): nothing to close cleanly
                    self.proc.terminate()
            except (BrokenPipeError, OSError, ValueError):
                pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        return self.proc.returncode


class Router:
    """``python -m apps.cli router`` as a child process."""

    def __init__(self, *args: str, argv_prefix: tuple[str, ...] = ()):
        env = dict(os.environ, PYTHONPATH=str(ROOT), RUST_LOG="error")
        self.proc = subprocess.Popen([*argv_prefix, sys.executable, "-m", "apps.cli", "router", *args,
                                      "--zenoh-set", "transport/shared_memory/enabled=false"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                     cwd=str(ROOT))
        self.banner = self.proc.stdout.readline()  # printed once the session is open
        if "zid" not in self.banner:
            self.stop()
            raise AssertionError(f"router did not start: {self.banner!r} {self.proc.stderr.read()[-2000:]}")

    def stop(self, sig=signal.SIGTERM) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            out, err = self.proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate(timeout=5)
        return self.proc.returncode, out + err


def lget_keys(agent: Agent, key: str, tries: int = 5) -> list[str]:
    """Keys of a liveliness query. Zenoh 1.10 clients sometimes answer the first liveliness
    query after a fresh declaration with nothing (seen without any ACL too), so ask again,
    a bounded number of times, until something comes back."""
    keys: list[str] = []
    for _ in range(tries):
        keys = sorted(r["key"] for r in agent.cmd("lget", key=key, timeout=2.0)["replies"])
        if keys:
            break
    return keys


def await_route(pub: Agent, sub: Agent, name: str, key: str, tries: int = 100) -> None:
    """Put probe samples on ``key`` from ``pub`` until ``sub``'s subscriber ``name`` gets one.

    Declarations travel asynchronously: a put sent right after another process declared its
    subscriber may reach the router first and be dropped. After this returns, the route
    ``pub`` → router → ``sub`` exists, so later puts (allowed or not) meet it."""
    for i in range(tries):
        pub.cmd("put", key=key, payload=f"{PROBE}{i}")
        got = sub.received(name, probes=True)
        if any(x["payload"].startswith(PROBE) for x in got):
            return
        time.sleep(0.1)
    raise AssertionError(f"no route {pub.name} -> {sub.name} on {key} after {tries} probes")


def get_replies(agent: Agent, key: str, tries: int = 50, **kw) -> list[dict]:
    """Replies of a query on ``key``, asked again (bounded) while there are none yet: the
    queryable's declaration may still be on its way to the router."""
    res: list[dict] = []
    for _ in range(tries):
        res = agent.cmd("get", key=key, **kw)["replies"]
        if res:
            break
        time.sleep(0.1)
    return res


if __name__ == "__main__":
    sys.exit(_child(json.loads(sys.argv[1])))
