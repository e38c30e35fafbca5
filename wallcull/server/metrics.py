"""The server's Prometheus metrics."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

class Metrics:
    def __init__(self):
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames = Counter("wallcull_frames", "Frames culled", registry=r)
        self.stage = Histogram("wallcull_stage_seconds", "Time per pipeline stage", ["stage"],
                               buckets=(1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2,
                                        5e-2, 0.1, 0.25, 1.0), registry=r)
        self.packets = Counter("wallcull_packets", "Packets sent", ["kind", "transport"],
                               registry=r)
        self.bytes = Counter("wallcull_packet_bytes", "Packet bytes sent", ["kind", "transport"],
                             registry=r)
        self.clients = Gauge("wallcull_clients_connected", "Streaming render nodes", registry=r)
        self._bound: dict = {}
        # status: the HTTP status of a refused request or handshake (JSON or a page); "ws": a
        # message on an open stream answered {"error"}; "nats": a NATS ack dropped or a node
        # message not published (docs/hardening.md)
        self.errors = Counter("wallcull_errors", "Requests refused", ["status"], registry=r)
        self.state_failing = Gauge(
            "wallcull_state_write_failing",
            "1 while the state folder cannot be written (disk full, read-only): see /health",
            registry=r)
        self.unavailable = Gauge("wallcull_walls_unavailable",
                                 "Walls of the state folder waiting for their scene", registry=r)
        self.expired = Counter("wallcull_walls_expired", "Walls deleted after --wall-ttl idle",
                               registry=r)

    def packet(self, delta: bool, size: int, transport: str):
        key = ("delta" if delta else "full", transport)
        bound = self._bound.get(key)
        if bound is None:  # labels() costs a lock and a dict lookup: bind each pair once
            bound = self._bound[key] = (self.packets.labels(*key), self.bytes.labels(*key))
        bound[0].inc()
        bound[1].inc(size)
