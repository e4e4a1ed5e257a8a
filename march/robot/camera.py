"""``python -m march.robot camera``: the policy's depth image from an Intel RealSense (the G1's
head camera family) or from a recording, through librealsense (pyrealsense2), on ``rt/march/depth``.

:class:`Preprocess` turns a camera frame (Z16 x the frame's depth units: planar depth in metres,
0 where the camera has no return) into the student's image as the training's camera sees it
(``deploy.json`` ``depth``): the student's pixel grid is laid over the camera's through both
intrinsics (pinhole, the same optical axis: the student's field of view must lie inside the
camera's), each student pixel the mean of the valid camera pixels under it (valid: finite and
> 0); fewer than half valid -> 0 (invalid: the loop maps it to ``max_range_m``, as training
maps a missed ray); valid values clipped to [``min_range_m``, ``max_range_m``]. The robot loop
normalises and flags an image that is mostly invalid (:func:`march.robot.wire_checks.depth_invalid_flag`).

Sources (:class:`SensorFrames`, the same code for both): ``source=realsense`` (the first
RealSense found, its depth sensor's Z16 stream of ``width`` x ``height`` at ``fps``), or
``source=file file=<recording.db3 | .bag>`` (librealsense's playback of a realsense-viewer or
``rs.recorder`` recording, at its recorded frame times). The mount is not corrected: the camera must look
along the student camera's axis (``deploy.json`` ``depth.pose_meaning``); docs/deploying.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from march.sim2sim.bundle_schema import UsageError

MIN_VALID_SHARE = 0.5
"""A student pixel needs at least this share of valid camera pixels under it, else invalid."""
DEFAULT_STREAM = (640, 480, 30)
"""width, height, fps of the RealSense depth stream (D435 / D435i: 640 x 480 at 30 Hz)."""


def realsense() -> Any:
    """pyrealsense2, with libusb from the ``libusb-package`` wheel where the system has none."""
    try:
        import pyrealsense2 as rs
    except ImportError as err:
        if "libusb" not in str(err):
            raise UsageError(
                f"pyrealsense2 is not installed ({err}): pip install 'march[camera]'"
            ) from None
        try:
            import ctypes

            import libusb_package

            ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
            import pyrealsense2 as rs
        except (ImportError, OSError):
            raise UsageError(
                "pyrealsense2 needs libusb-1.0: apt install libusb-1.0-0, or "
                "pip install libusb-package"
            ) from None
    return rs


@dataclass(frozen=True)
class Pinhole:
    """A camera's pixel grid: size and intrinsics [px] (pixel centres at integer + 0.5)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def of_student(cls, depth: dict[str, Any]) -> Pinhole:
        k = depth["intrinsics"]
        return cls(
            int(depth["width"]),
            int(depth["height"]),
            k["fx_px"],
            k["fy_px"],
            k["cx_px"],
            k["cy_px"],
        )

    @classmethod
    def of_realsense(cls, intr: Any) -> Pinhole:
        return cls(int(intr.width), int(intr.height), intr.fx, intr.fy, intr.ppx, intr.ppy)


class Preprocess:
    """A camera frame in metres -> the student's image in metres (0: invalid)."""

    def __init__(self, depth: dict[str, Any], camera: Pinhole) -> None:
        self.student, self.camera = Pinhole.of_student(depth), camera
        self.lo, self.hi = float(depth["min_range_m"]), float(depth["max_range_m"])
        s, c = self.student, camera
        # student pixel edges -> camera pixel coordinates (same ray: (u - cx) / fx)
        cols = c.cx + (np.arange(s.width + 1) - s.cx) / s.fx * c.fx
        rows = c.cy + (np.arange(s.height + 1) - s.cy) / s.fy * c.fy
        if (
            cols[0] < -0.5
            or rows[0] < -0.5
            or cols[-1] > c.width + 0.5
            or rows[-1] > c.height + 0.5
        ):
            raise UsageError(
                f"the camera's field of view ({c.width}x{c.height}, fx {c.fx:.1f}) does not "
                f"cover the student's ({s.width}x{s.height}, fx {s.fx:.1f})"
            )
        # each camera pixel belongs to the student pixel its centre falls in
        self.col_at = np.clip(np.ceil(cols - 0.5).astype(int), 0, c.width)
        self.row_at = np.clip(np.ceil(rows - 0.5).astype(int), 0, c.height)
        if (np.diff(self.col_at) < 1).any() or (np.diff(self.row_at) < 1).any():
            raise UsageError(
                f"the camera ({c.width}x{c.height}) is coarser than the student's image "
                f"({s.width}x{s.height}) over its field of view"
            )

    def __call__(self, metres: np.ndarray) -> np.ndarray:
        c = self.camera
        if metres.shape != (c.height, c.width):
            raise UsageError(f"a frame of {metres.shape}, the camera's is {(c.height, c.width)}")
        r0, r1, c0, c1 = self.row_at[0], self.row_at[-1], self.col_at[0], self.col_at[-1]
        crop = np.asarray(metres, dtype=np.float64)[r0:r1, c0:c1]
        valid = np.isfinite(crop) & (crop > 0)
        value = np.where(valid, crop, 0.0)

        def blocks(a: np.ndarray) -> np.ndarray:
            a = np.add.reduceat(a, self.row_at[:-1] - r0, axis=0)
            return np.add.reduceat(a, self.col_at[:-1] - c0, axis=1)

        total, count = blocks(value), blocks(valid.astype(np.float64))
        size = np.outer(np.diff(self.row_at), np.diff(self.col_at))
        ok = count >= MIN_VALID_SHARE * size
        mean = np.divide(total, count, out=np.zeros_like(total), where=count > 0)
        return np.where(ok, np.clip(mean, self.lo, self.hi), 0.0)


class SensorFrames:
    """Depth frames of a librealsense sensor (a RealSense's, a recording's playback, a software
    device's) as (frame number, metres, :class:`Pinhole`)."""

    def __init__(
        self, rs: Any, sensor: Any, stream: tuple[int, int, int] | None, pace: bool = False
    ) -> None:
        profiles = [
            p.as_video_stream_profile()
            for p in sensor.get_stream_profiles()
            if p.stream_type() == rs.stream.depth and p.format() == rs.format.z16
        ]
        if stream is not None:
            w, h, fps = stream
            profiles = [p for p in profiles if (p.width(), p.height(), p.fps()) == (w, h, int(fps))]
        if not profiles:
            raise UsageError(f"the depth sensor has no Z16 stream {stream or ''}")
        self.rs, self.sensor, self.profile = rs, sensor, profiles[0]
        self.pinhole = Pinhole.of_realsense(self.profile.get_intrinsics())
        self.queue = rs.frame_queue(64, keep_frames=True)
        self.pace, self.first = pace, None  # pace: a recording, read as fast as it is taken
        self.started = False
        if not pace:  # a live sensor streams at once; a recording waits for start()
            self.start()

    def start(self) -> None:
        """Stream into the queue (a recording's playback begins here), once."""
        if not self.started:
            self.sensor.open(self.profile)
            self.sensor.start(self.queue)
            self.started = True

    def next(self, timeout_s: float) -> tuple[int, np.ndarray] | None:
        try:
            frame = self.queue.wait_for_frame(int(timeout_s * 1000))
        except RuntimeError:
            return None
        if self.pace:  # at the recorded times (librealsense's real-time playback drops frames)
            stamp = float(frame.get_timestamp()) / 1e3
            if self.first is None:
                self.first = (stamp, time.perf_counter())
            wait = self.first[1] + stamp - self.first[0] - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        depth = frame.as_depth_frame()
        z16 = np.asanyarray(depth.get_data())
        return int(frame.get_frame_number()), z16.astype(np.float64) * float(depth.get_units())

    def close(self) -> None:
        self.sensor.stop()
        self.sensor.close()


MAX_RECORDING_BYTES = 64 << 30
"""A recording's size bound: an hour of 640 x 480 Z16 depth at 30 Hz is ~66 GB raw, ~20 GB in
librealsense's compressed rosbag."""


def check_recording(path: Path) -> None:
    """``file=``: a regular file (not a symbolic link: what is checked is what is read) of a
    recording's suffix and at most :data:`MAX_RECORDING_BYTES`, through the disk gate; one line."""
    from march.store.bounded_read import FileRefused, open_regular

    if path.suffix not in (".db3", ".bag"):
        raise UsageError(f"file={path}: not a librealsense recording (.db3 / .bag)")
    try:
        open_regular(path, f"file={path}", MAX_RECORDING_BYTES, "a .db3 / .bag recording").close()
    except FileRefused as err:
        raise UsageError(str(err)) from None


def open_source(args: dict[str, Any]) -> tuple[SensorFrames, Any]:
    kind = args.get("source", "realsense")
    if kind == "file":
        path = Path(args.get("file", ""))
        check_recording(path)
        rs = realsense()
        try:
            device = rs.context().load_device(str(path))
            playback = device.as_playback()
            playback.set_real_time(False)
            sensor = device.first_depth_sensor()
        except RuntimeError as err:  # librealsense's refusal of a file it cannot play
            first = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise UsageError(f"file={path}: not a librealsense recording ({first})") from None
        return SensorFrames(rs, sensor, None, pace=True), device
    rs = realsense()
    devices = list(rs.context().query_devices())
    if not devices:
        raise UsageError("no RealSense found (source=realsense); source=file file=<recording>")
    fps = args.get("fps", DEFAULT_STREAM[2])
    stream = (*DEFAULT_STREAM[:2], int(fps))
    return SensorFrames(rs, devices[0].first_depth_sensor(), stream), devices[0]


def serve(
    frames: SensorFrames,
    pre: Preprocess,
    domain: int,
    interface: str,
    seconds: float = math.inf,
    idle_s: float = 2.0,
    wait_for_reader_s: float = 5.0,
    discovery_settle_s: float = 0.5,
) -> dict[str, float]:
    """Publish every frame until ``seconds`` pass, SIGINT / SIGTERM, or ``idle_s`` without one
    (a recording's end, an unplugged camera). A recording not yet started replays once a reader
    of the topic is matched and ``discovery_settle_s`` more have passed, or after
    ``wait_for_reader_s`` without one."""
    from march.robot import dds
    from march.robot.signals import stop_on_signals
    from march.robot.wire_checks import depth_invalid_flag

    dp = dds.participant(domain, interface)
    out = dds.writer(dp, dds.DEPTH_TOPIC, dds.DepthImage_)
    if not frames.started:
        # A recording's replay waits (up to wait_for_reader_s) for a reader of the topic to be
        # discovered before its first frame: best-effort samples written before discovery are
        # lost, so a consumer started with the replay missed its first frames on a busy machine.
        end = time.monotonic() + wait_for_reader_s
        while not out.get_matched_subscriptions() and time.monotonic() < end:
            time.sleep(0.01)
        readers = len(out.get_matched_subscriptions())
        if readers:
            # Discovery is two-sided: this writer matched the reader, but the reader may not
            # have matched this writer yet, and a best-effort sample reaching a reader that does
            # not know its writer is dropped (frame 0 went missing on a loaded machine with the
            # writer-side wait alone, 2026-12-07).
            time.sleep(discovery_settle_s)
        print(f"[camera] replay starts with {readers} reader(s) of {dds.DEPTH_TOPIC}", flush=True)
        frames.start()
    stop, _ = stop_on_signals()
    t0 = time.perf_counter()
    n, mostly, invalid = 0, 0, 0.0
    h, w = pre.student.height, pre.student.width
    print(
        f"[camera] {pre.camera.width}x{pre.camera.height} -> {w}x{h} on {dds.DEPTH_TOPIC}, "
        f"domain {domain}, interface {interface}",
        flush=True,
    )
    while not stop["flag"] and time.perf_counter() - t0 < seconds:
        got = frames.next(idle_s)
        if got is None:
            break
        number, metres = got
        image = pre(metres)
        out.write(dds.DepthImage_(number % 2**32, h, w, [float(v) for v in image.reshape(-1)]))
        n += 1
        invalid += float((image <= 0).mean())
        mostly += depth_invalid_flag(image) is not None
    return {"frames": n, "mostly_invalid": mostly, "mean_invalid": invalid / max(n, 1)}


def main(args: dict[str, Any]) -> int:
    from march.robot.supervisor import read_spec

    spec = read_spec(args["bundle"])
    frames, device = open_source(args)
    try:
        pre = Preprocess(spec["depth"], frames.pinhole)
        stats = serve(
            frames,
            pre,
            args.get("domain", 0),
            args.get("interface", "eth0"),
            args.get("seconds", math.inf),
            wait_for_reader_s=float(args.get("wait_for_reader_s", 5.0)),
        )
    finally:
        frames.close()
        del device
    print(
        f"[camera] done: {stats['frames']} frames, {stats['mean_invalid']:.1%} invalid pixels on "
        f"average, {stats['mostly_invalid']} images mostly invalid",
        flush=True,
    )
    return 0
