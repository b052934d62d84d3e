"""Foxglove bridge node: the running graph served over Foxglove's WebSocket protocol.

Subscribes to every topic (``graph/status`` included, for the log panel), converts each message
with :class:`nodes.foxglove_convert.FoxgloveConverter` (one clock, ``/tf`` frames) and logs the
records on ``foxglove.Channel``s of a ``foxglove-sdk`` WebSocket server (loopback by default).
The server speaks the WebSocket subprotocol ``foxglove.sdk.v1`` only (Foxglove's app offers it;
clients written for the older ``foxglove.websocket.v1`` must ask for the new one). Open
Foxglove, "Open connection" > "Foxglove WebSocket" > the printed ``ws://`` address, and import
``docs/foxglove_layout.json``.

The bridge keeps the latest record of every channel and sends it again when a client
subscribes: a viewer opened after the scan still sees its images and result, and one opened
before the graph started, which subscribes when a channel first appears, still gets that
channel's first message (clients already subscribed may see that record twice).

``python -m nodes.foxglove_bridge port:=8766``; in a launch file, ``foxglove:=true
foxglove_port:=8766``.
"""

from __future__ import annotations

import sys
import threading
from typing import Any

import foxglove
from foxglove.websocket import ServerListener

from msgs import now_ns
from nodes.foxglove_convert import FoxgloveConverter, FoxgloveMessage
from nodes.runtime.node import Node, run_node
from nodes.runtime.params import Param
from twinfocus.errors import TwinFocusError


class FoxgloveBridge(Node):
    """Serve the graph's topics to Foxglove over WebSocket."""

    NAME = "foxglove_bridge"
    PARAMS = {
        **Node.PARAMS,
        "host": Param(
            "127.0.0.1",
            "interface to listen on (loopback by default; 0.0.0.0 exposes the graph to the network)",
            type="str",
        ),
        "port": Param(8766, "WebSocket port (0 = any free port; 8765 is the visualizer's page)", type="int"),
        "trajectory_every": Param(10, "send the whole trajectory after this many poses", type="int"),
        "calibration": Param(
            {},
            "calibration as the recorder takes it ({extrinsics: T_camera_radar}): the radar -> camera frame",
            type="any",
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)

        self._fox = foxglove
        self.context = foxglove.Context()
        calib = self.params["calibration"]
        if not isinstance(calib, dict):
            raise TwinFocusError(f"node {self.name!r}: parameter 'calibration' must be a mapping, got {calib!r}")
        self.converter = FoxgloveConverter(
            trajectory_every=self.params["trajectory_every"], extrinsics=calib.get("extrinsics") or None
        )
        self._channels: dict[str, Any] = {}
        self._latched: dict[str, FoxgloveMessage] = {}
        self._resend: list[str] = []
        self._lock = threading.Lock()
        bridge = self

        class _Listener(ServerListener):
            # Called on the server's thread: only note the topic; the node loop logs it (logging
            # from inside the callback would re-enter the server).
            def on_subscribe(self, client, channel) -> None:
                with bridge._lock:
                    bridge._resend.append(channel.topic)

        try:
            self.server = foxglove.start_server(
                name="twinfocus",
                host=self.params["host"],
                port=self.params["port"],
                server_listener=_Listener(),
                context=self.context,
            )
        except Exception as exc:  # the SDK raises its own error types for a taken port
            raise TwinFocusError(
                f"node {self.name!r}: cannot serve Foxglove on {self.params['host']}:{self.params['port']} ({exc})"
            ) from None
        self.port = self.server.port
        self.create_subscription("*", self._on_message)
        self.create_timer(0.1, self._flush_resends)

    def _on_message(self, topic: str, msg: Any) -> None:
        if topic.startswith("graph/") and topic != "graph/status":
            return
        for rec in self.converter.convert(topic, msg, now_ns()):
            self._log(rec)
            with self._lock:
                self._latched[rec.topic] = rec

    def _log(self, rec: FoxgloveMessage) -> None:
        ch = self._channels.get(rec.topic)
        if ch is None:
            schema = self._fox.Schema(name=rec.schema_name, encoding=rec.schema_encoding, data=rec.schema_data)
            ch = self._fox.Channel(
                rec.topic, schema=schema, message_encoding=rec.message_encoding, context=self.context
            )
            self._channels[rec.topic] = ch
        ch.log(rec.data, log_time=rec.log_time_ns)

    def _flush_resends(self) -> None:
        with self._lock:
            topics, self._resend = self._resend, []
            recs = [self._latched[t] for t in dict.fromkeys(topics) if t in self._latched]
        for rec in recs:
            self._log(rec)

    def on_start(self) -> None:
        self.log(
            f"Foxglove: open connection > Foxglove WebSocket > ws://{self.params['host']}:{self.port} "
            "(layout: docs/foxglove_layout.json)"
        )

    def on_shutdown(self) -> None:
        self.server.stop()


def main(argv: list[str] | None = None) -> int:
    return run_node(FoxgloveBridge, argv)


if __name__ == "__main__":
    sys.exit(main())
