"""Learning: PPO teacher runner (rsl-rl's PPO), distillation algorithm and runner, checkpoints."""
