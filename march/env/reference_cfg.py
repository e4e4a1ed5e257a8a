"""Where tools that read the ``reference`` command's defaults without building an env have found
its configuration: :class:`march.env.reference_command.ReferenceCommandCfg`, which now lives
beside its term (mjlab's layout: a command term and its config in one module; issue 54 untied
the circle reference_cfg <-> reference_command). New code imports it from there."""

from __future__ import annotations

from march.env.reference_command import ReferenceCommandCfg

__all__ = ["ReferenceCommandCfg"]
