"""mjlab's browser viewer (viser) on a march env and policy (``python -m march.play viewer=viser``).

mjlab's own ``ViserPlayViewer`` runs the loop: play / pause / step / reset / speed, the scene,
the ``Rewards`` tab (march's reward terms, live bars and plots, from the env's reward manager),
the ``Metrics`` tab and the debug-visualization toggles. march adds its plan drawing
(:mod:`march.env.plan_drawing`) through the ``reference`` command term's debug visualization,
and an adapter giving the bare ``ManagerBasedRlEnv`` the ``get_observations`` the viewer asks for
(mjlab's play wraps its env in rsl-rl's wrapper; march's policies read the observation dict).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class ViewerEnv:
    """The env as mjlab's viewer expects it (``EnvProtocol``), observations as a dict."""

    def __init__(self, env: Any) -> None:
        self._env = env
        self.num_envs = env.num_envs

    @property
    def unwrapped(self) -> Any:
        return self._env

    @property
    def device(self) -> Any:
        return self._env.device

    @property
    def cfg(self) -> Any:
        return self._env.cfg

    def get_observations(self) -> Any:
        obs = getattr(self._env, "obs_buf", None)
        return obs if obs else self._env.observation_manager.compute()

    def step(self, actions: Any) -> tuple[Any, ...]:
        return self._env.step(actions)

    def reset(self) -> Any:
        return self._env.reset()

    def close(self) -> None:
        self._env.close()


GUI_AXES = ("lin_vel_x", "lin_vel_y", "ang_vel_z")
SLIDER_MIN = 0.1
"""mjlab's velocity joystick makes a "Max <axis>" slider on [0.1, 10] starting at the range's
upper end: viser refuses a start below 0.1, which the evaluation's fixed command (lateral and
yaw ranges (0, 0)) has."""


def _gui_safe_velocity_sliders(env: Any) -> None:
    """Let velocity command terms build their joystick with upper ends of at least 0.1: the
    ranges are raised while the GUI is made and put back at once (sampling is unchanged)."""
    import copy

    for term in env.command_manager._terms.values():
        ranges = getattr(term.cfg, "ranges", None)
        if ranges is None or not all(hasattr(ranges, a) for a in GUI_AXES):
            continue
        make = term.create_gui

        def create_gui(*args: Any, _term: Any = term, _make: Any = make, **kw: Any) -> Any:
            kept = _term.cfg.ranges
            shown = copy.copy(kept)
            for axis in GUI_AXES:
                lo, hi = getattr(kept, axis)
                setattr(shown, axis, (lo, max(hi, SLIDER_MIN)))
            _term.cfg.ranges = shown
            try:
                return _make(*args, **kw)
            finally:
                _term.cfg.ranges = kept

        term.create_gui = create_gui


def open_viewer(
    env: Any,
    policy: Callable[[Any], Any],
    host: str = "0.0.0.0",
    port: int = 8080,
    steps: int | None = None,
    on_ready: Callable[[str], None] | None = None,
) -> int:
    """Serve mjlab's viser viewer for ``env`` driven by ``policy`` until Ctrl-C (or ``steps``
    control steps when given). The plan is drawn. Returns the control steps run."""
    import viser
    from mjlab.viewer.base import VerbosityLevel
    from mjlab.viewer.viser.viewer import ViserPlayViewer

    from march.env.plan_drawing import enable_plan_drawing

    enable_plan_drawing(env)
    _gui_safe_velocity_sliders(env)
    server = viser.ViserServer(host=host, port=port, label="march", verbose=False)
    viewer = ViserPlayViewer(
        ViewerEnv(env), policy, verbosity=VerbosityLevel.SILENT, viser_server=server
    )
    if on_ready is not None:
        on_ready(f"http://{'localhost' if host in ('0.0.0.0', '') else host}:{server.get_port()}")
    try:
        viewer.run(num_steps=steps)
    finally:
        server.stop()
    return int(viewer._step_count)
