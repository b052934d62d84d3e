"""Launch files: start the broker and a graph of nodes, stop all of it cleanly.

A launch file is readable YAML (see ``launch/sim.yaml``)::

    description: one line
    arguments:                    # name: {default: ..., help: ...}; no default = required
      port: {default: 7447, help: broker port on loopback}
    broker: tcp://127.0.0.1:$(arg port)
    nodes:
      - name: solver              # unique; also the prefix of its output lines
        node: solver              # a type of nodes.NODE_TYPES, or a module path
        parameters: {size: $(arg size)}
        on_exit: shutdown         # optional: when this node ends, stop the graph
        enabled: $(arg record)    # optional: false, 0, "" or "no" leave the node out

``$(arg NAME)`` is replaced by an argument (keeping its YAML type when it is the whole
value), ``$(env NAME)`` / ``$(env NAME default)`` by an environment variable.

:func:`run` starts the broker in this process, each node as a child process (its own session,
so a terminal's Ctrl-C reaches only the launcher, which then stops the nodes in order; and a
parent-death signal, so no node outlives a killed launcher), prefixes their output with
``[name]``, and stops everything on Ctrl-C, SIGTERM, a node crash (non-zero exit) or the end
of an ``on_exit: shutdown`` node: SIGINT first, SIGTERM after ``grace_s``, SIGKILL last.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from nodes import NODE_TYPES
from nodes.bus import Broker
from nodes.node import ENV_GRAPH_NODES, ENV_LAUNCHED
from nodes.params import parse_assignment
from twinfocus.errors import TwinFocusError

LAUNCH_DIR = Path(__file__).resolve().parent.parent / "launch"
_SUBST = re.compile(r"\$\((arg|env)\s+([A-Za-z_][A-Za-z0-9_]*)(?:\s+([^)]*))?\)")


@dataclass
class NodeSpec:
    name: str
    module: str
    parameters: dict[str, Any] = field(default_factory=dict)
    on_exit: str = "ignore"  # "ignore" | "shutdown"


@dataclass
class Graph:
    path: Path
    description: str
    broker: str
    nodes: list[NodeSpec]
    arguments: dict[str, Any]


def find_launch_file(name: str | os.PathLike) -> Path:
    """A path, or a name in the repository's ``launch/`` folder (``sim`` -> launch/sim.yaml)."""
    p = Path(name)
    if p.is_file():
        return p
    for cand in (LAUNCH_DIR / p, LAUNCH_DIR / f"{p}.yaml"):
        if cand.is_file():
            return cand
    raise TwinFocusError(f"{name}: no such launch file (the bundled ones are in {LAUNCH_DIR})")


def _truthy(value: Any) -> bool:
    """``enabled:`` values: false, 0, "", "false", "no", "0" and null disable a node."""
    if isinstance(value, str):
        return value.strip().lower() not in ("", "false", "no", "0", "off", "null", "none")
    return bool(value)


def _substitute(value: Any, args: dict[str, Any], where: str) -> Any:
    if isinstance(value, dict):
        return {k: _substitute(v, args, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, list):
        return [_substitute(v, args, f"{where}[{i}]") for i, v in enumerate(value)]
    if not isinstance(value, str):
        return value

    def lookup(kind: str, name: str, default: str | None) -> Any:
        if kind == "arg":
            if name not in args:
                raise TwinFocusError(f"{where}: $(arg {name}) is not a declared argument")
            return args[name]
        v = os.environ.get(name, default)
        if v is None:
            raise TwinFocusError(f"{where}: environment variable {name} is not set and has no default")
        return v

    m = _SUBST.fullmatch(value.strip())
    if m:  # the whole value: keep the argument's type (number, list, bool)
        return lookup(m.group(1), m.group(2), m.group(3))
    return _SUBST.sub(lambda m: str(lookup(m.group(1), m.group(2), m.group(3))), value)


def load(path: str | os.PathLike, assignments: list[str] | tuple = ()) -> Graph:
    """Read a launch file and resolve its arguments (``name:=value`` strings override defaults)."""
    path = find_launch_file(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise TwinFocusError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("nodes"), list) or not doc["nodes"]:
        raise TwinFocusError(f"{path}: a launch file needs a 'nodes:' list")
    declared = doc.get("arguments") or {}
    if not isinstance(declared, dict):
        raise TwinFocusError(f"{path}: 'arguments' must be a mapping name -> {{default, help}}")
    given = dict(parse_assignment(a) for a in assignments)
    unknown = sorted(set(given) - set(declared))
    if unknown:
        known = ", ".join(f"{k} (default {v.get('default')!r})" if isinstance(v, dict) and "default" in v else k for k, v in declared.items())
        raise TwinFocusError(f"{path}: unknown argument(s) {', '.join(unknown)}; known: {known}")
    args: dict[str, Any] = {}
    for name, spec in declared.items():
        spec = spec if isinstance(spec, dict) else {"default": spec}
        if name in given:
            args[name] = given[name]
        elif "default" in spec:
            args[name] = spec["default"]
        else:
            raise TwinFocusError(f"{path}: argument {name!r} is required ({spec.get('help', 'no help')}); pass {name}:=VALUE")
    broker = str(_substitute(doc.get("broker", "tcp://127.0.0.1:7447"), args, "broker"))
    nodes: list[NodeSpec] = []
    seen: set[str] = set()
    for i, entry in enumerate(doc["nodes"]):
        where = f"{path}: nodes[{i}]"
        if not isinstance(entry, dict) or "node" not in entry:
            raise TwinFocusError(f"{where}: each node needs at least 'node:' (its type) and 'name:'")
        entry = _substitute(entry, args, where)
        if not _truthy(entry.get("enabled", True)):
            continue
        kind = str(entry["node"])
        module = NODE_TYPES.get(kind, kind)
        if "." not in module:
            raise TwinFocusError(f"{where}: unknown node type {kind!r}; known: {', '.join(NODE_TYPES)}")
        name = str(entry.get("name", kind))
        if name in seen:
            raise TwinFocusError(f"{where}: duplicate node name {name!r}")
        seen.add(name)
        params = entry.get("parameters") or {}
        if not isinstance(params, dict):
            raise TwinFocusError(f"{where}: 'parameters' must be a mapping")
        on_exit = str(entry.get("on_exit", "ignore"))
        if on_exit not in ("ignore", "shutdown"):
            raise TwinFocusError(f"{where}: on_exit must be 'ignore' or 'shutdown', got {on_exit!r}")
        nodes.append(NodeSpec(name, module, params, on_exit))
    if not nodes:
        raise TwinFocusError(f"{path}: every node is disabled")
    return Graph(path, str(doc.get("description", "")), broker, nodes, args)


class _Output:
    """Prefix every line of the children's output with their name (one writer at a time)."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stdout
        self.lock = threading.Lock()
        self.width = 0

    def line(self, name: str, text: str) -> None:
        with self.lock:
            self.stream.write(f"[{name}]".ljust(self.width + 2) + " " + text.rstrip("\n") + "\n")
            self.stream.flush()

    def pump(self, name: str, pipe) -> None:
        for raw in iter(pipe.readline, b""):
            self.line(name, raw.decode(errors="replace"))
        pipe.close()


def _pdeathsig() -> None:  # runs in the child before exec
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


class Launcher:
    """Runs a :class:`Graph`; :meth:`run` blocks until the graph stops and returns an exit code."""

    def __init__(self, graph: Graph, grace_s: float = 10.0, stream=None):
        self.graph = graph
        self.grace_s = grace_s
        self.out = _Output(stream)
        self.out.width = max(len(n.name) for n in graph.nodes + [NodeSpec("launch", "")])
        self.procs: dict[str, subprocess.Popen] = {}
        self.pumps: list[threading.Thread] = []
        self.broker: Broker | None = None
        self._stop_reason: str | None = None
        self._code = 0

    def say(self, text: str) -> None:
        self.out.line("launch", text)

    def _on_signal(self, signum, frame) -> None:
        if self._stop_reason is None:
            self._stop_reason = f"{signal.Signals(signum).name} received"

    def start(self) -> None:
        self.broker = Broker(self.graph.broker).start()
        self.say(f"broker on {self.broker.endpoint} (data ports {self.broker.xsub_port}, {self.broker.xpub_port})")
        env = dict(os.environ)
        env[ENV_GRAPH_NODES] = ",".join(n.name for n in self.graph.nodes)
        env[ENV_LAUNCHED] = "1"
        env["PYTHONUNBUFFERED"] = "1"
        # Repository root on the path, so `python -m nodes.x` works from any directory.
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        for spec in self.graph.nodes:
            cmd = [sys.executable, "-m", spec.module, "--name", spec.name, "--broker", self.broker.endpoint,
                   "--params", json.dumps(spec.parameters)]
            p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 env=env, start_new_session=True, preexec_fn=_pdeathsig)
            self.procs[spec.name] = p
            t = threading.Thread(target=self.out.pump, args=(spec.name, p.stdout), daemon=True)
            t.start()
            self.pumps.append(t)
            self.say(f"started {spec.name} ({spec.module}, pid {p.pid})")

    def run(self) -> int:
        in_main = threading.current_thread() is threading.main_thread()
        old = {}
        if in_main:
            for sig in (signal.SIGINT, signal.SIGTERM):
                old[sig] = signal.signal(sig, self._on_signal)
        try:
            self.start()
            self._watch()
        finally:
            self._stop_all()
            if in_main:
                for sig, h in old.items():
                    signal.signal(sig, h)
        return self._code

    def request_stop(self, reason: str = "stop requested") -> None:
        if self._stop_reason is None:
            self._stop_reason = reason

    def _watch(self) -> None:
        specs = {n.name: n for n in self.graph.nodes}
        running = set(self.procs)
        while running:
            if self._stop_reason is not None:
                self.say(f"{self._stop_reason}: stopping the graph")
                return
            for name in sorted(running):
                code = self.procs[name].poll()
                if code is None:
                    continue
                running.discard(name)
                if code != 0:
                    what = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
                    self.say(f"node {name!r} {what}; stopping the graph")
                    self._code = 1
                    return
                if specs[name].on_exit == "shutdown":
                    self.say(f"node {name!r} finished; stopping the graph (on_exit: shutdown)")
                    return
                self.say(f"node {name!r} finished")
            time.sleep(0.05)
        self.say("every node finished")

    def _stop_all(self) -> None:
        alive = {n: p for n, p in self.procs.items() if p.poll() is None}
        for sig, wait in ((signal.SIGINT, self.grace_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if not alive:
                break
            if sig == signal.SIGKILL:
                self.say(f"killing {', '.join(alive)} (did not stop in time)")
            for p in alive.values():
                try:
                    p.send_signal(sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while alive and time.monotonic() < deadline:
                alive = {n: p for n, p in alive.items() if p.poll() is None}
                time.sleep(0.05)
        for t in self.pumps:
            t.join(timeout=2)
        if self.broker is not None:
            self.broker.stop()
            self.broker = None
        if self.procs:
            self.say("graph stopped")


def run(path: str | os.PathLike, assignments: list[str] | tuple = (), grace_s: float = 10.0) -> int:
    """Load and run a launch file; returns the exit code (0 clean, 1 a node failed)."""
    graph = load(path, assignments)
    return Launcher(graph, grace_s=grace_s).run()
