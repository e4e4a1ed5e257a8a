"""Test helper: a Hydra callback that records every job's return value (what a sweeper reads).

+hydra.callbacks.returns._target_=tests.sweep_returns.RecordReturns
+hydra.callbacks.returns.path=<file>
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback


class RecordReturns(Callback):
    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        with self.path.open("a") as f:
            value = job_return.return_value if job_return.status.name == "COMPLETED" else None
            out_dir = config.hydra.runtime.output_dir
            f.write(json.dumps({"dir": str(out_dir), "value": value}) + "\n")
