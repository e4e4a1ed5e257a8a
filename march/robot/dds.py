"""DDS plumbing: a participant on one network interface, the robot's topics, the depth topic.

``participant(domain, interface)`` joins DDS ``domain`` bound to ``interface`` (``lo`` for the
MuJoCo robot on this machine, the robot's Ethernet, e.g. ``eth0``, for a G1), as Unitree's
``ChannelFactoryInitialize(domain, interface)`` does, through a cyclonedds XML configuration.
:class:`Latest` keeps the newest sample of a topic and when it arrived (polled by the loop,
never blocking it). Depth travels on a project topic
(:class:`DepthImage_`): a real camera driver publishes the same type, or fills a
:class:`march.robot.policy_loop.DepthSource` in-process.
"""

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

DEPTH_TOPIC = "rt/march/depth"
SIM_STATE_TOPIC = "rt/march/sim_state"
SUPERVISOR_TOPIC = "rt/march/supervisor"


@dataclass
class DepthImage_(IdlStruct, typename="march::msg::dds_::DepthImage_"):
    """A planar depth image in metres (0: no return), row-major, row 0 at the top."""

    tick: t.uint32 = 0
    height: t.uint16 = 0
    width: t.uint16 = 0
    depth_m: t.sequence[t.float32] = field(default_factory=list)


@dataclass
class Heartbeat_(IdlStruct, typename="march::msg::dds_::Heartbeat_"):
    """The supervisor's heartbeat (every control period): its pid, a counter, and whether it has
    taken over (``took_over`` 1: it is damping the robot; the policy loop damps too)."""

    pid: t.uint32 = 0
    seq: t.uint32 = 0
    took_over: t.uint8 = 0


_DOMAINS: dict[int, Domain] = {}


def config_xml(interface: str) -> str:
    return (
        "<CycloneDDS><Domain><General><Interfaces>"
        f'<NetworkInterface name="{interface}" priority="default" multicast="default"/>'
        "</Interfaces></General></Domain></CycloneDDS>"
    )


def participant(domain: int, interface: str) -> DomainParticipant:
    """A participant of ``domain`` on ``interface`` (one Domain object per process and id)."""
    if domain not in _DOMAINS:
        _DOMAINS[domain] = Domain(domain, config_xml(interface))
    return DomainParticipant(domain)


def best_effort(depth: int = 1) -> Qos:
    """Unitree's low-level topics: best effort, keep the last sample."""
    return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(depth))


class Latest:
    """The newest sample of a topic and when it was taken (perf_counter). Polled, not a
    listener: cyclonedds 11's listener callbacks raced the reader's creation and teardown
    here (a callback with no reader, then SIGSEGV in one run of three)."""

    def __init__(self, dp: DomainParticipant, name: str, kind: type, qos: Qos | None = None):
        self.kind = kind
        self.sample: Any = None
        self.arrived: float | None = None
        self.count = 0
        self.pending: deque[Any] = deque(maxlen=256)  # taken since the last drain(), in order
        self.topic = Topic(dp, name, kind)
        self.reader = DataReader(dp, self.topic, qos=qos or best_effort())

    def poll(self) -> bool:
        """Take what has arrived; True if a new valid sample did."""
        samples = [s for s in self.reader.take(N=64) if isinstance(s, self.kind)]
        if not samples:
            return False
        self.sample, self.arrived = samples[-1], time.perf_counter()
        self.count += len(samples)
        self.pending.extend(samples)
        return True

    def drain(self) -> list[Any]:
        """Every sample taken since the last call, oldest first (at most the last 256)."""
        out = list(self.pending)
        self.pending.clear()
        return out

    def take(self) -> tuple[Any, float | None]:
        """The newest sample so far and when it was taken (polls first)."""
        self.poll()
        return self.sample, self.arrived

    def wait(self, timeout: float, interval: float = 5e-4) -> bool:
        """Poll until a new sample arrives or ``timeout`` passes."""
        end = time.perf_counter() + timeout
        while True:
            if self.poll():
                return True
            if time.perf_counter() >= end:
                return False
            time.sleep(interval)


def writer(dp: DomainParticipant, name: str, kind: type, qos: Qos | None = None) -> DataWriter:
    return DataWriter(dp, Topic(dp, name, kind), qos=qos or best_effort())
