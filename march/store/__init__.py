"""What lives on disk, and the one door every tool reads it through (SPEC section 9).

Run directories, their lock and status, checkpoints and deployment bundles. Every tool
(``march.train`` with ``resume=`` or a new run in an existing directory, ``march.play``,
``march.export``, ``march.sim2sim``, ``march.robot``, ``march.inspect run``, ``analysis/``) reads
them through these functions, so that one crafted file gets the same one-line refusal from
every tool:

- checkpoints: :func:`march.store.gate.read_checkpoint` (no link, bounded size, plain data,
  entries and config checked, the modules it names named by the user too, weights against its
  config) and :func:`march.store.gate.policy_from_checkpoint` (then its policy applied); the
  checks that read no record, without torch, first: :mod:`march.store.checkpoint_file` (a
  crafted file is refused before torch is imported);
- a run's saved config against a new one: :func:`march.store.resume_rules.resume_config`,
  :func:`~march.store.resume_rules.adopt_config`, one copy of the rules in
  :func:`~march.store.resume_rules.check_changes`;
- a run directory: :func:`march.store.run_dir.before_hydra`, :func:`~march.store.run_dir.claim`,
  :func:`~march.store.run_dir.check_run_checkpoints`; its lock :mod:`march.store.run_lock`; its
  status :func:`march.store.status.read_status` / :func:`~march.store.status.write_status`;
- any file: :mod:`march.store.bounded_read` (no link, size bounded before reading, strict JSON,
  gzip inflated within a bound).

Nothing is imported here: the robot-side readers (``march.sim2sim``) and ``analysis/`` load only
the standard-library modules they use, not torch.
"""
