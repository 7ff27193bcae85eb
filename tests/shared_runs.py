"""The settings of the runs that tests/conftest.py makes once per session for the tests of several modules."""

TINY_WALKER_RUN = dict(
    env="walker-walk", frames=800, action_repeat=20, seed_frames=400, batch_size=16, hidden_dim=64, size=48,
    eval_every_frames=400, eval_episodes=1, progress_bar=False, replay_sampling="sb3", collapse_metrics_every_frames=0,
    snapshots=True, torch_threads=1,
)  # fmt: skip
"""800 frames (40 agent steps at action repeat 20: evaluation episodes of 50 agent steps) at 48x48, updates from
agent step 20, evaluated at frames 0 and 400 and the final model at 800, with a snapshot of the encoder and actor
at each of the three."""
