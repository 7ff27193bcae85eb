"""The rl_zoo3 launcher: rl_zoo3's ``train`` and ``enjoy`` scripts with DrQv2 registered (docs/zoo.md)."""

from __future__ import annotations

import argparse
import difflib
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sb3_collapse.commands.cli import prog_name
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.errors import InputError, MissingDependencyError
from sb3_collapse.paper import PAPER
from sb3_collapse.presets import PRESETS
from sb3_collapse.zoo.registration import ALGO_NAME, register_with_zoo

PROG = prog_name("sb3_collapse.zoo")
COMMANDS = ("train", "enjoy")
_DRQV2 = PRESETS["walker-walk"]  # the evaluation protocol is the same for every task
DRQV2_EVAL_FREQ = _DRQV2.eval_every_frames // _DRQV2.action_repeat  # DrQ-v2's evaluation period, in agent steps
SWITCHES = {  # the launcher's own options (every other one goes to rl_zoo3) and the callbacks they add
    "--collapse-metrics": {"sb3_collapse.monitoring.CollapseMetrics": {"check_every_frames": PAPER.check_every_frames}},
    "--reset-rule": {
        "sb3_collapse.monitoring.CollapseReset": {
            "window_frames": PAPER.window_frames, "check_every_frames": PAPER.check_every_frames, "verbose": 1
        }
    },
}  # fmt: skip

USAGE = f"{PROG} {{train,enjoy}} [--collapse-metrics] [--reset-rule] [rl_zoo3 options]"
DESCRIPTION = (
    "Run rl_zoo3's train or enjoy script with DrQv2 registered as --algo drqv2 and the DeepMind Control ids "
    "(sb3_collapse/<domain>-<task>-v0) available. Every other option goes to rl_zoo3 unchanged: "
    f"`{PROG} train --help` lists them. Counts are in agent steps (frames / action repeat)."
)
EPILOG = (
    f"With --algo drqv2: train needs -conf (e.g. zoo_configs/drqv2.yml), evaluates every {DRQV2_EVAL_FREQ} agent "
    f"steps on {_DRQV2.eval_episodes} episodes unless --eval-freq / --eval-episodes say otherwise (DrQ-v2's "
    f"{_DRQV2.eval_every_frames:,} frames at action repeat {_DRQV2.action_repeat}), and refuses -optimize; enjoy "
    "runs with --no-render (the DeepMind Control envs render off-screen only)."
)


def build_parser() -> argparse.ArgumentParser:
    """The launcher's own command line: the sub-command and the collapse switches (rl_zoo3 parses the rest)."""
    parser = argparse.ArgumentParser(prog=PROG, usage=USAGE, description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("command", choices=COMMANDS, help="the rl_zoo3 script to run")
    switches = parser.add_argument_group("collapse monitoring (train only)")
    switches.add_argument(
        "--collapse-metrics",
        action="store_true",
        help="add sb3_collapse.monitoring.CollapseMetrics to the config's callbacks: the collapse metrics of every "
        f"named layer (collapse/<layer>/..., to TensorBoard with -tb) every {PAPER.check_every_frames:,} frames",
    )
    switches.add_argument(
        "--reset-rule",
        action="store_true",
        help=f"add sb3_collapse.monitoring.CollapseReset (the paper's reset rule: window {PAPER.window_frames:,} "
        f"frames, {PAPER.layer} gradient-norm threshold {PAPER.threshold:g}, patience {PAPER.patience}, a check every "
        f"{PAPER.check_every_frames:,} frames) to the config's callbacks",
    )
    return parser


def _peek(zoo_args: list[str]) -> argparse.Namespace:
    """:return: the few rl_zoo3 options of ``zoo_args`` that the launcher reads (they still go to rl_zoo3)"""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--algo", default="ppo")
    parser.add_argument("--env")
    parser.add_argument("-conf", "--conf-file")
    parser.add_argument("-optimize", "--optimize-hyperparameters", dest="optimize", action="store_true")
    parser.add_argument("--eval-freq")
    parser.add_argument("--eval-episodes")
    parser.add_argument("--no-render", action="store_true")
    return parser.parse_known_args(zoo_args)[0]


def collapse_callbacks(collapse_metrics: bool, reset_rule: bool) -> list[dict[str, dict[str, Any]]]:
    """``CollapseMetrics`` and ``CollapseReset`` (the paper's rule) as wanted, in rl_zoo3's ``callback`` format."""
    return [callback for wanted, callback in zip((collapse_metrics, reset_rule), SWITCHES.values()) if wanted]


def _train_arguments(zoo_args: list[str]) -> list[str]:
    """``zoo_args`` and, for ``--algo drqv2``, DrQ-v2's evaluation period and episodes; checks first."""
    peek = _peek(zoo_args)
    if peek.algo != ALGO_NAME or "-h" in zoo_args or "--help" in zoo_args:
        return list(zoo_args)
    if peek.conf_file is None:
        raise InputError("--algo drqv2 needs a config file: pass -conf zoo_configs/drqv2.yml (or your own).")
    if peek.optimize:
        raise InputError("-optimize is not available for drqv2: rl_zoo3 has no hyperparameter sampler for it.")
    _check_env_and_config(peek.env, peek.conf_file)
    args = list(zoo_args)
    if peek.eval_freq is None:
        args += ["--eval-freq", str(DRQV2_EVAL_FREQ)]
    if peek.eval_episodes is None:
        args += ["--eval-episodes", str(_DRQV2.eval_episodes)]
    return args


def _check_env_and_config(env_id: str | None, conf_file: str) -> None:
    """Before rl_zoo3 starts: ``env_id`` is registered (or ``None``), ``conf_file`` a YAML mapping with its entry."""
    import gymnasium as gym
    import yaml

    import sb3_collapse.envs  # noqa: F401  registers the sb3_collapse/<domain>-<task>-v0 ids

    if env_id is not None and env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=3, cutoff=0.6)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        raise InputError(
            f"--env {env_id} is not a registered Gymnasium id.{hint} The DeepMind Control ids are "
            "sb3_collapse/<domain>-<task>-v0, e.g. sb3_collapse/walker-walk-v0."
        )
    path = Path(conf_file)
    if not path.is_file():
        raise InputError(f"-conf {conf_file} is not a file; pass zoo_configs/drqv2.yml or your own YAML file.")
    try:
        config = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise InputError(f"-conf {conf_file} is not a YAML file ({str(error).splitlines()[0]}).") from None
    if not isinstance(config, dict):
        raise InputError(f"-conf {conf_file} must map env ids to hyperparameters (rl_zoo3's format).")
    if env_id is not None and env_id not in config:
        raise InputError(f"-conf {conf_file} has no entry for {env_id}; add one or choose another --env.")


def _enjoy_arguments(zoo_args: list[str]) -> list[str]:
    """``zoo_args`` with ``--no-render`` for ``--algo drqv2`` (the DeepMind Control envs cannot open a window)."""
    peek = _peek(zoo_args)
    return [*zoo_args, *(["--no-render"] if peek.algo == ALGO_NAME and not peek.no_render else [])]


@contextmanager
def _replaced(owner: Any, name: str, value: Any) -> Iterator[None]:
    """Set ``owner.name`` to ``value`` for the duration of the block, then restore it."""
    saved = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, saved)


def run_train(zoo_args: list[str], callbacks: list[dict[str, dict[str, Any]]]) -> None:
    """rl_zoo3's ``train`` with ``zoo_args``, ``callbacks`` after the config's, CUDA flags as the train command's."""
    import rl_zoo3.train

    from sb3_collapse.backends import configure_backends
    from sb3_collapse.zoo.experiment import ZooExperimentManager

    configure_backends()  # the train command's defaults: TF32 and cuDNN's autotuner on CUDA
    manager = ZooExperimentManager.with_callbacks(callbacks)
    # rl_zoo3's scripts parse sys.argv, and train() builds the ExperimentManager named in its module.
    with _replaced(sys, "argv", [f"{PROG} train", *zoo_args]), _replaced(rl_zoo3.train, "ExperimentManager", manager):
        rl_zoo3.train.train()


def _error(message: str) -> int:
    """Print ``message`` as argparse prints an error; :return: exit status 2"""
    print(f"usage: {USAGE}\n{PROG}: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """:return: exit status (2 for a bad command line or config, rl_zoo3's own status when its parser exits)"""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    if not argv:
        return _error("missing sub-command: train or enjoy (--help for more).")
    if argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        return _error(f"unknown sub-command {command!r}: choose from {', '.join(COMMANDS)}.")
    switches = {name: name in rest for name in SWITCHES}
    zoo_args = [arg for arg in rest if arg not in SWITCHES]
    if command == "enjoy" and any(switches.values()):
        return _error("--collapse-metrics and --reset-rule are train options.")
    if "-h" in zoo_args or "--help" in zoo_args:
        parser.print_help()
        print(f"\nrl_zoo3 {command} options:")
    # The OpenGL backend before rl_zoo3 is imported; its SubprocVecEnv workers inherit MUJOCO_GL from os.environ.
    ensure_rendering_backend(required=False)
    try:
        register_with_zoo()
        if command == "train":
            run_train(_train_arguments(zoo_args), collapse_callbacks(*switches.values()))
        else:
            import rl_zoo3.enjoy

            with _replaced(sys, "argv", [f"{PROG} enjoy", *_enjoy_arguments(zoo_args)]):
                rl_zoo3.enjoy.enjoy()
    except (InputError, MissingDependencyError) as error:
        return _error(str(error))
    except SystemExit as exit_:  # rl_zoo3's argparse: --help, or a bad option (it printed why)
        return exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 2)
    return 0
