"""Launch files: start the broker and a graph of nodes, stop all of it cleanly.

A launch file is readable YAML (see ``launch/sim.yaml``)::

    description: one line
    include: [paper.yaml]         # optional: files whose arguments this one shares (below)
    arguments:                    # name: {default: ..., help: ...}; no default = required
      port: {default: 7447, help: broker port on loopback}
    broker: tcp://127.0.0.1:$(arg port)
    nodes:
      - name: solver              # unique; also the prefix of its output lines
        node: solver              # a type of nodes.NODE_TYPES, or a module path
        parameters: {size: $(arg size)}
        on_exit: shutdown         # optional: what its end means (below)
        respawn: true             # optional: restart it when it ends (as ROS 2 launch's respawn)
        respawn_delay: 1.0        # optional: seconds before a restart (default 1)
        respawn_max: 3            # optional: restarts allowed before the graph stops (default 3)
        enabled: $(arg record)    # optional: false, 0, "" or "no" leave the node out

``on_exit`` says what a node's end (while the graph runs, not stopped by the launcher) means:
``shutdown``: its work is the graph's, stop the graph (exit 0 when it ended with status 0);
``ignore``: let the others run on; ``fail``: it must not end, stop the graph with exit status 1.
The default is ``ignore`` for the types of :data:`nodes.FINISHING_TYPES` (the player) and
``fail`` for every other (drivers, synchronizer, solver: the graph stalls without them). A
node that crashes (non-zero status) always stops the graph unless it is respawned; the
launcher's status is then 2 when the node reported a user error (status 2), else 1.

``include:`` lists argument files (paths relative to the including file's folder, as ROS 2
launch resolves ``$(dirname)/...``): YAML holding only ``description`` and ``arguments``, whose
declarations the including file gets as if it declared them itself. The bundled launch files
take the paper's regions, image size and iterations from ``launch/paper.yaml`` this way. An
argument is declared in one place: the same name in two of them is an error.

``$(arg NAME)`` is replaced by an argument (keeping its YAML type when it is the whole
value), ``$(env NAME)`` / ``$(env NAME default)`` by an environment variable. :func:`load`
checks, before any node starts, every ``name:=value`` against the type of the argument's
default and every node's parameters against the parameters its class declares
(:func:`nodes.runtime.params.resolve`), so a bad value is one line (exit 2), not a traceback per node.

:func:`run` starts the broker in this process, each node as a child process (its own session,
so a terminal's Ctrl-C reaches only the launcher, which then stops the nodes in order; and a
parent-death signal, so no node outlives a killed launcher), prefixes their output with
``[name]``, and stops everything on Ctrl-C, SIGTERM, a node crash (non-zero exit) or the end
of a node whose ``on_exit`` says so: SIGTERM first, SIGKILL once a node has been silent (no
heartbeat) for ``grace_s`` -- a node still heartbeating while it ends (the solver focusing the part
of a scan that arrived) is given up to ``max_stop_s``. Nodes also poll their parent pid, so they
notice a dead launcher within 0.1 s even if the signal was missed.

A failed run: the launcher names the node that stopped first and exits 1. A node stopped by a
signal that is not the launcher's says so in every heartbeat from then on (while it may still
finish its work: the solver focusing what arrived), so it is named before a node that ends
because of it (the visualizer handed that incomplete result); of nodes that ended together, one
that failed is named before one that finished. Before it stops the other nodes the launcher
tells the broker why the run failed (:meth:`nodes.runtime.bus.Broker.fail`), which the recorder asks to
keep an earlier log.

Hung nodes: the broker keeps every node's latest heartbeat (nodes send one every ``heartbeat_s``,
also from long computations). A node silent for ``stall_s`` (at least three periods) whose process
is stopped (SIGSTOP) or has used no CPU time for another ``stall_s`` (blocked) is hung; a node that
computes is given ``hang_s`` of silence. A hung node is named in one line, killed, and respawned
where the launch file says ``respawn``; otherwise the graph stops with status 1.
"""

from __future__ import annotations

import importlib
import json
import math
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

from nodes import FINISHING_TYPES, NODE_TYPES
from nodes.runtime.bus import Broker
from nodes.runtime.node import ENV_GRAPH_NODES, ENV_LAUNCHED, ENV_LAUNCHER_PID, Node, stop_signals_to
from nodes.runtime.params import REQUIRED, Param, coerce, parse_assignment, resolve
from twinfocus.errors import TwinFocusError

LAUNCH_DIR = Path(__file__).resolve().parents[2] / "launch"
_SUBST = re.compile(r"\$\((arg|env)\s+([A-Za-z_][A-Za-z0-9_]*)(?:\s+([^)]*))?\)")


@dataclass
class NodeSpec:
    name: str
    module: str
    parameters: dict[str, Any] = field(default_factory=dict)
    on_exit: str = "fail"  # "fail" | "ignore" | "shutdown" (see the module docstring)
    respawn: bool = False
    respawn_delay_s: float = 1.0
    respawn_max: int = 3


@dataclass
class Graph:
    path: Path
    description: str
    broker: str
    nodes: list[NodeSpec]
    arguments: dict[str, Any]


def find_launch_file(name: str | os.PathLike) -> Path:
    """A path, or a bundled launch file: ``sim``, ``sim.yaml`` or ``launch/sim.yaml`` (relative
    to the repository, as README writes it) name launch/sim.yaml from any working folder."""
    p = Path(name)
    if p.is_file():
        return p.resolve()
    if not p.is_absolute():
        for cand in (LAUNCH_DIR / p, LAUNCH_DIR / f"{p}.yaml", LAUNCH_DIR.parent / p):
            if cand.is_file():
                return cand
    if not LAUNCH_DIR.is_dir():
        raise TwinFocusError(
            f"{name}: no such launch file (the bundled launch files come with the repository's "
            f"launch/ folder, which this installation lacks: give a launch file's path)"
        )
    bundled = ", ".join(sorted(q.stem for q in LAUNCH_DIR.glob("*.yaml") if _is_launch_file(q)))
    raise TwinFocusError(f"{name}: no such launch file (bundled in {LAUNCH_DIR}: {bundled})")


def _is_launch_file(path: Path) -> bool:
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and "nodes" in doc


def _read_yaml(path: Path, what: str) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except OSError as exc:
        raise TwinFocusError(f"{path}: cannot read the {what} ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise TwinFocusError(f"{path}: not valid YAML ({exc})") from None


def _declarations(path: Path, doc: dict) -> dict[str, Any]:
    """The arguments ``doc`` (read from ``path``) declares, its ``include:`` files' first."""
    includes = doc.get("include") or []
    if isinstance(includes, str):
        includes = [includes]
    if not isinstance(includes, list) or not all(isinstance(x, str) for x in includes):
        raise TwinFocusError(f"{path}: 'include' must be a file name or a list of them")
    declared: dict[str, Any] = {}
    source: dict[str, Path] = {}

    def add(names: dict, where: Path) -> None:
        for name, spec in names.items():
            if name in declared:
                raise TwinFocusError(
                    f"{where}: argument {name!r} is also declared in {source[name]}; declare it in one place"
                )
            declared[name], source[name] = spec, where

    for entry in includes:
        inc = path.parent / entry  # an absolute entry stays absolute
        if not inc.is_file():
            raise TwinFocusError(f"{path}: included file {entry!r} not found (looked for {inc})")
        sub = _read_yaml(inc, "included file")
        extra = sorted(set(sub) - {"description", "arguments"}) if isinstance(sub, dict) else None
        if extra is None or extra or not isinstance(sub.get("arguments"), dict):
            raise TwinFocusError(
                f"{inc}: an included file holds only 'description' and an 'arguments' mapping"
                + (f" (found {', '.join(extra)})" if extra else "")
            )
        add(sub["arguments"], inc)
    own = doc.get("arguments") or {}
    if not isinstance(own, dict):
        raise TwinFocusError(f"{path}: 'arguments' must be a mapping name -> {{default, help}}")
    add(own, path)
    return declared


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
    doc = _read_yaml(path, "launch file")
    if not isinstance(doc, dict) or not isinstance(doc.get("nodes"), list) or not doc["nodes"]:
        raise TwinFocusError(f"{path}: a launch file needs a 'nodes:' list")
    declared = _declarations(path, doc)
    given = dict(parse_assignment(a) for a in assignments)
    unknown = sorted(set(given) - set(declared))
    if unknown:
        known = ", ".join(
            f"{k} (default {v.get('default')!r})" if isinstance(v, dict) and "default" in v else k
            for k, v in declared.items()
        )
        raise TwinFocusError(f"{path}: unknown argument(s) {', '.join(unknown)}; known: {known}")
    args: dict[str, Any] = {}
    for name, spec in declared.items():
        spec = spec if isinstance(spec, dict) else {"default": spec}
        if name in given:
            args[name] = _check_argument(path, name, spec, given[name])
        elif "default" in spec:
            args[name] = spec["default"]
        else:
            raise TwinFocusError(
                f"{path}: argument {name!r} is required ({spec.get('help', 'no help')}); pass {name}:=VALUE"
            )
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
        on_exit = str(entry.get("on_exit", "ignore" if kind in FINISHING_TYPES else "fail"))
        if on_exit not in ("fail", "ignore", "shutdown"):
            raise TwinFocusError(f"{where}: on_exit must be 'fail', 'ignore' or 'shutdown', got {on_exit!r}")
        respawn = entry.get("respawn", False)
        if not isinstance(respawn, bool):
            raise TwinFocusError(f"{where}: respawn must be true or false, got {respawn!r}")
        try:
            delay, most = float(entry.get("respawn_delay", 1.0)), int(entry.get("respawn_max", 3))
        except (TypeError, ValueError):
            raise TwinFocusError(f"{where}: respawn_delay must be seconds and respawn_max a count") from None
        if not (delay >= 0 and most >= 0):
            raise TwinFocusError(f"{where}: respawn_delay and respawn_max must be >= 0")
        nodes.append(NodeSpec(name, module, params, on_exit, respawn, delay, most))
    if not nodes:
        raise TwinFocusError(f"{path}: every node is disabled")
    for spec in nodes:
        _check_parameters(path, spec)
    return Graph(path, str(doc.get("description", "")), broker, nodes, args)


def _check_argument(path: Path, name: str, spec: dict, value: Any) -> Any:
    """A launch argument given as ``name:=value``, as the type of its declared default (a number,
    true/false, a list of numbers) and within its declared ``min`` / ``max``; a number that is
    not finite or out of bounds is refused in one line before any node starts. Arguments
    without a default or with a text default take any value (the nodes check them)."""
    default = spec.get("default")
    if default is None or isinstance(default, str):
        return value
    kind = None
    if isinstance(default, (list, tuple)):
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in default)
        kind = "floats" if default and numbers else "list"
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    label = f"{path.name}: argument {name} (default {default!r})"
    checked = coerce(label, Param(default, type=kind), value)
    if isinstance(checked, float) and math.isnan(checked):
        raise TwinFocusError(f"{label} must be a number, got {value!r}")
    low, high = spec.get("min"), spec.get("max")
    if isinstance(checked, (int, float)) and not isinstance(checked, bool):
        if (low is not None and checked < low) or (high is not None and checked > high):
            bounds = " and ".join(w for w in (low is not None and f">= {low}", high is not None and f"<= {high}") if w)
            raise TwinFocusError(f"{label} must be {bounds}, got {value!r}")
    return value if kind == "list" else checked


def _check_parameters(path: Path, spec: NodeSpec) -> None:
    """The node's parameters against what its class declares (:func:`nodes.runtime.params.resolve`:
    names, types, choices; a required one left out is the node's to refuse), so a bad value is
    one line before any node starts, not a traceback from each node that takes it. A node class
    that cannot be imported here is left to say so itself when it starts."""

    try:
        module = importlib.import_module(spec.module)
    except Exception:
        return
    classes = [
        c
        for c in vars(module).values()
        if isinstance(c, type) and issubclass(c, Node) and c is not Node and c.__module__ == module.__name__
    ]
    if len(classes) != 1:
        return
    cls = classes[0]
    try:
        # a required parameter left out is the node's own one-line refusal (it names the argument)
        declared = {k: p for k, p in cls.PARAMS.items() if p.default is not REQUIRED or k in spec.parameters}
        resolve(spec.name, declared, spec.parameters, (), cls.RENAMED_PARAMS)
    except TwinFocusError as exc:
        raise TwinFocusError(f"{path.name}: {exc}") from None


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


def _exit_text(code: int) -> str:
    def name(n):
        try:
            return signal.Signals(n).name
        except ValueError:
            return f"signal {n}"

    if code < 0:
        return f"was killed by {name(-code)}"
    if code > 128 and code - 128 < 65:
        return f"was stopped by {name(code - 128)} from outside the launcher (status {code})"
    return f"exited with status {code}"


def _pdeathsig() -> None:  # runs in the child before exec
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


class Launcher:
    """Runs a :class:`Graph`; :meth:`run` blocks until the graph stops and returns an exit code."""

    def __init__(
        self,
        graph: Graph,
        grace_s: float = 10.0,
        stream=None,
        stall_s: float = 3.0,
        hang_s: float = 60.0,
        max_stop_s: float = 120.0,
    ):
        self.graph = graph
        self.grace_s = grace_s
        self.stall_s = stall_s
        self.hang_s = hang_s
        self.max_stop_s = max(max_stop_s, grace_s)
        self._quiet: dict[str, tuple[float, int]] = {}  # silent node -> (since, its CPU ticks then)
        self.out = _Output(stream)
        self.out.width = max(len(n.name) for n in graph.nodes + [NodeSpec("launch", "")])
        self.procs: dict[str, subprocess.Popen] = {}
        self.pumps: list[threading.Thread] = []
        self.broker: Broker | None = None
        self._stop_reason: str | None = None
        self._code = 0
        self._failure = ""  # the line that named the node whose stop failed the run

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
        env[ENV_LAUNCHER_PID] = str(os.getpid())
        env["PYTHONUNBUFFERED"] = "1"
        # Repository root on the path, so `python -m nodes.x` works from any directory.
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.env = env
        for spec in self.graph.nodes:
            self._spawn(spec)

    def _spawn(self, spec: NodeSpec) -> None:
        assert self.broker is not None, "nodes are spawned after the broker starts"
        cmd = [
            sys.executable,
            "-m",
            spec.module,
            "--name",
            spec.name,
            "--broker",
            self.broker.endpoint,
            "--params",
            json.dumps(spec.parameters),
        ]
        p = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=self.env,
            start_new_session=True,
            preexec_fn=_pdeathsig,
        )
        self.procs[spec.name] = p
        t = threading.Thread(target=self.out.pump, args=(spec.name, p.stdout), daemon=True)
        t.start()
        self.pumps.append(t)
        self.say(f"started {spec.name} ({spec.module}, pid {p.pid})")

    def run(self) -> int:
        with stop_signals_to(self._on_signal):
            return self._run()

    def _run(self) -> int:
        try:
            self.start()
            self._watch()
        finally:
            if self._code and self.broker is not None:
                # before any node is stopped: the recorder asks for it to keep the earlier log
                self.broker.fail(self._failure or f"the graph failed (status {self._code})")
            self._stop_all()
        return self._code

    def request_stop(self, reason: str = "stop requested") -> None:
        if self._stop_reason is None:
            self._stop_reason = reason

    def _watch(self) -> None:
        specs = {n.name: n for n in self.graph.nodes}
        running = set(self.procs)
        respawns = {name: 0 for name in specs}
        due: dict[str, float] = {}  # node -> when to respawn it

        def respawn_or_stop(name: str, what: str, code: int) -> bool:
            """Schedule a respawn where the launch file allows one; else say why the graph stops.
            True: the graph goes on."""
            spec = specs[name]
            if spec.respawn and respawns[name] < spec.respawn_max:
                respawns[name] += 1
                self.say(
                    f"node {name!r} {what}; respawning it in {spec.respawn_delay_s:g} s "
                    f"(respawn {respawns[name]} of {spec.respawn_max})"
                )
                due[name] = time.monotonic() + spec.respawn_delay_s
                return True
            if spec.respawn:
                fail(f"node {name!r} {what} and was respawned {spec.respawn_max} time(s) already", code)
            else:
                fail(f"node {name!r} {what}", code)
            return False

        def fail(what: str, code: int = 1) -> None:
            self._failure = what
            self.say(f"{what}; stopping the graph")
            self._code = 2 if code == 2 else 1

        while running or due:
            if self._stop_reason is not None:
                self.say(f"{self._stop_reason}: stopping the graph")
                return
            for name, when in sorted(due.items()):
                if time.monotonic() >= when:
                    del due[name]
                    self._spawn(specs[name])
                    running.add(name)
            beats = self.broker.heartbeats() if self.broker is not None else {}
            outside = self._stopped_from_outside(running, specs, beats)
            if outside:
                fail(outside)
                return
            # the nodes that ended since the last pass, failures first: a node that finished
            # because another one stopped (the visualizer, handed an incomplete result) is not
            # the one to name
            ended = {n: self.procs[n].poll() for n in running}
            order = sorted(running, key=lambda n: (ended[n] is None or (ended[n] == 0 and not specs[n].respawn), n))
            for name in order:
                p = self.procs[name]
                code = ended[name]
                if code is None:
                    why = self._hang(name, specs[name], p, beats.get(name))
                    if why is None:
                        continue
                    p.kill()  # a stopped or blocked process cannot act on SIGTERM
                    p.wait()
                    running.discard(name)
                    if not respawn_or_stop(name, f"stopped answering ({why})", 1):
                        return
                    continue
                running.discard(name)
                spec = specs[name]
                what = _exit_text(code) + self._last_word(name, p.pid)
                if spec.respawn or code != 0:
                    if not respawn_or_stop(name, what, code):
                        return
                    continue
                if spec.on_exit == "shutdown":
                    # a node stopped from outside just before may not have been heard from yet
                    time.sleep(0.3)
                    beats = self.broker.heartbeats() if self.broker is not None else {}
                    outside = self._stopped_from_outside(running, specs, beats)
                    if outside:
                        fail(outside)
                        return
                    self.say(f"node {name!r} finished; stopping the graph (on_exit: shutdown)")
                    return
                if spec.on_exit == "fail":
                    fail(
                        f"node {name!r} ended while the graph runs, and the graph cannot work without it "
                        "(set on_exit: ignore or respawn: true in the launch file to allow it)"
                    )
                    return
                self.say(f"node {name!r} finished")
            time.sleep(0.05)
        self.say("every node finished")

    def _stopped_from_outside(self, running: set[str], specs: dict[str, NodeSpec], beats: dict) -> str:
        """The line naming a running node that says it was stopped by a signal not the
        launcher's ("" for none). Its heartbeats say so from the signal on (nodes.runtime.node), while
        it may still be finishing its work; a node that is respawned is judged when it ends."""
        for name in sorted(running):
            hb = beats.get(name) or {}
            msg = str(hb.get("message") or "")
            if specs[name].respawn or hb.get("pid") != self.procs[name].pid or not msg.startswith("received SIG"):
                continue
            sig = msg.split()[1] if len(msg.split()) > 1 else "a signal"
            return f"node {name!r} was stopped by {sig} from outside the launcher"
        return ""

    def _last_word(self, name: str, pid: int) -> str:
        """': <reason>' from the final heartbeat of a node that ended with a reason (as the
        visualizer that counted a dropped scan), else ''."""
        deadline = time.monotonic() + 0.5  # its final heartbeat may still be on its way to the broker
        while self.broker is not None:
            hb = self.broker.heartbeats().get(name) or {}
            if hb.get("pid") == pid and hb.get("state") in ("stopped", "error"):
                msg = str(hb.get("message") or "")
                return f": {msg}" if msg and not msg.startswith("received SIG") else ""
            if time.monotonic() > deadline:
                return ""
            time.sleep(0.02)
        return ""

    def _hang(self, name: str, spec: NodeSpec, proc: subprocess.Popen, hb: dict | None) -> str | None:
        """Why the live node ``name`` counts as hung, or None.

        A node heartbeats every ``heartbeat_s`` from its loop and from long computations. Silent
        for ``stall_s`` (at least three periods) it is hung when its process is stopped (SIGSTOP,
        a debugger) or has used no CPU time for another ``stall_s`` (blocked); a busy node is given
        ``hang_s`` of silence, so a long computation on a loaded machine is not mistaken for a hang.
        """
        if hb is None or hb.get("pid") != proc.pid or hb.get("state") in ("stopped", "error"):
            self._quiet.pop(name, None)  # not heard from yet (starting), or its end is on its way
            return None
        now = time.monotonic()
        silent = now - float(hb["heard_s"])
        try:
            period = float(spec.parameters.get("heartbeat_s", 1.0))
        except (TypeError, ValueError):
            period = 1.0
        if silent < max(self.stall_s, 3 * period):
            self._quiet.pop(name, None)
            return None
        st = _proc_state(proc.pid)
        if st is None:  # it has just ended: the exit is handled on the next pass
            return None
        state, ticks = st
        if state in "Tt":
            return f"no heartbeat for {silent:.1f} s; its process is stopped (SIGSTOP or a debugger)"
        since, ticks0 = self._quiet.setdefault(name, (now, ticks))
        if ticks != ticks0:
            self._quiet[name] = (now, ticks)
        elif hb.get("state") != "stopping" and now - since >= self.stall_s:
            return f"no heartbeat for {silent:.1f} s and no CPU time used for {now - since:.1f} s (blocked)"
        if silent > self.hang_s:
            return f"no heartbeat for {silent:.1f} s though it computes (a loop that never returns?)"
        return None

    def _stop_all(self) -> None:
        alive = {n: p for n, p in self.procs.items() if p.poll() is None}
        # SIGTERM, not SIGINT: a node still importing dies of it quietly, where SIGINT would print
        # a KeyboardInterrupt traceback; a running node stops cleanly on either.
        for p in alive.values():
            try:
                p.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
        start = time.monotonic()
        killed: dict[str, subprocess.Popen] = {}
        while alive:
            now = time.monotonic()
            beats = self.broker.heartbeats() if self.broker is not None else {}
            late = []
            for n, p in alive.items():
                hb = beats.get(n) or {}
                heard = float(hb["heard_s"]) if hb.get("pid") == p.pid and "heard_s" in hb else start
                # grace_s of silence, not of time: a node still heartbeating (the solver focusing
                # what arrived) finishes, up to max_stop_s
                if now - max(start, heard) > self.grace_s or now - start > self.max_stop_s:
                    late.append(n)
            if late:
                self.say(f"killing {', '.join(late)} (did not stop in time)")
                for n in late:
                    try:
                        alive[n].kill()
                    except ProcessLookupError:
                        pass
                    killed[n] = alive.pop(n)
            alive = {n: p for n, p in alive.items() if p.poll() is None}
            time.sleep(0.05)
        for p in killed.values():
            try:
                p.wait(3.0)
            except subprocess.TimeoutExpired:
                pass
        for t in self.pumps:
            t.join(timeout=2)
        if self.broker is not None:
            self.broker.stop()
            self.broker = None
        if self.procs:
            self.say(f"graph stopped: failed ({self._failure})" if self._failure else "graph stopped")


def _proc_state(pid: int) -> tuple[str, int] | None:
    """(state letter, user + system CPU ticks) of process ``pid`` from /proc, None if gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields[0], int(fields[11]) + int(fields[12])


def run(path: str | os.PathLike, assignments: list[str] | tuple = (), grace_s: float = 10.0) -> int:
    """Load and run a launch file; returns the exit code (0 clean, 1 a node failed, 2 a node
    reported a user error)."""
    graph = load(path, assignments)
    return Launcher(graph, grace_s=grace_s).run()
