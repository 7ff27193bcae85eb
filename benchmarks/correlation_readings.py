"""The three readings of the paper's correlation (Section 5.1, "the average correlation among every two non-zero
activations"; ``CORRELATION_READINGS`` of ``sb3_collapse/monitoring/metrics.py``) on constructed layers and on the
snapshots of a run, to choose the one Figures 4, 8, 9 draw (docs/figures.md).

Constructed layers: ``relu(W z + b)``, ``W`` a ``(width, dim)`` Gaussian map (std ``1/sqrt(dim)``: pre-activations of
unit variance for a unit-variance ``z``), ``b`` zero ("no bias") or Gaussian of std ``--bias-std`` ("bias"), on
``--samples`` inputs ``z``:

- *collapsed, k directions*: ``z = z0 + eps (c_1 v_1 + ... + c_k v_k)``, one fixed point ``z0 ~ N(0, I)``, ``v`` ``k``
  orthonormal directions, ``c ~ N(0, 1)``, ``eps`` = ``--eps`` (the features "collapse to a single point");
- *healthy*: ``z ~ N(0, I)`` (random features of inputs that differ);
- *exact*: ``z = z0`` for every input (every input maps to one point).

Snapshots (``--run-dir``): every snapshot of a train run (``--snapshots``) on the fixed set of Figures 4, 8, 9 drawn
from a rollouts file (``--rollouts``, of ``python -m sb3_collapse.probe record``) as the report draws it
(``FixedInputSettings``; ``--train-episodes``: the probe's training episodes, Figure 1's H), beside the run's
evaluation return and its training-time collapse check at the same frame (mlp1's gradient norm, the actions' spread
and saturation on the check's replay batch).

    python benchmarks/correlation_readings.py                         # constructed layers only
    python benchmarks/correlation_readings.py --run-dir RUN --rollouts RUN/rollouts.npz
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch as th

from sb3_collapse.commands.report_pipelines import FixedInputSettings
from sb3_collapse.monitoring import CORRELATION_READINGS, dead_units, layer_metrics
from sb3_collapse.paper import metric_tag
from sb3_collapse.probe.fixed_inputs import fixed_metrics
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, SNAPSHOT_FILE, snapshot_files
from sb3_collapse.report.collapse_figure import run_folder_trial
from sb3_collapse.runfolder import read_collapse_metrics


def constructed_layer(
    directions: int | None, bias: bool, samples: int, width: int, dim: int, eps: float, bias_std: float, seed: int
) -> th.Tensor:
    """:return: ``(samples, width)`` activations ``relu(W z + b)`` (module docstring; ``directions`` ``None``:
    healthy, 0: exact collapse)"""
    gen = th.Generator().manual_seed(seed)
    weight = th.randn(width, dim, generator=gen, dtype=th.float64) / math.sqrt(dim)
    offset = bias_std * th.randn(width, generator=gen, dtype=th.float64) if bias else th.zeros(width, dtype=th.float64)
    if directions is None:
        z = th.randn(samples, dim, generator=gen, dtype=th.float64)
    else:
        point = th.randn(dim, generator=gen, dtype=th.float64)
        z = point.expand(samples, dim).clone()
        if directions:
            basis, _ = th.linalg.qr(th.randn(dim, directions, generator=gen, dtype=th.float64))  # (dim, k) orthonormal
            z += eps * th.randn(samples, directions, generator=gen, dtype=th.float64) @ basis.T
    return th.relu(z @ weight.T + offset)


def _fmt(value: float) -> str:
    return "NaN" if math.isnan(value) else f"{value:.3f}"


def constructed_table(args: argparse.Namespace) -> list[str]:
    """:return: the markdown rows of the constructed layers"""
    lines = [
        (
            f"constructed layers: relu(W z + b), width {args.width}, z in R^{args.dim}, {args.samples} inputs, "
            f"eps {args.eps:g}, bias std {args.bias_std:g}"
        ),
        "",
        "| layer | bias | " + " | ".join(CORRELATION_READINGS) + " | dead units |",
        "|---|---|" + "---|" * (len(CORRELATION_READINGS) + 1),
    ]
    cases = [("healthy (random features)", None)] + [(f"collapsed, {k} directions", k) for k in args.directions]
    cases.append(("exact collapse (one point)", 0))
    for name, directions in cases:
        for bias in (False, True):
            h = constructed_layer(directions, bias, args.samples, args.width, args.dim, args.eps, args.bias_std, 0)
            values = layer_metrics(h, metrics=CORRELATION_READINGS)
            cells = " | ".join(_fmt(values[reading]) for reading in CORRELATION_READINGS)
            lines.append(f"| {name} | {'yes' if bias else 'no'} | {cells} | {dead_units(h)} |")
    return lines


def snapshot_table(args: argparse.Namespace) -> list[str]:
    """:return: the markdown rows of the run's snapshots"""
    settings = FixedInputSettings(
        fixed_samples=args.samples or None, device="cpu", layers=tuple(args.layers), train_episodes=args.train_episodes
    )
    inputs = settings.load(args.rollouts)
    trial = run_folder_trial(args.run_dir)
    returns = dict(zip(trial.frames.tolist(), trial.returns.tolist()))
    online_tags = [metric_tag("mlp1", "grad_norm"), "collapse/action_std", "collapse/action_saturation"]
    online = read_collapse_metrics(Path(args.run_dir) / COLLAPSE_METRICS_CSV, online_tags)
    online_at = {tag: dict(zip(f.tolist(), v.tolist())) for tag, (f, v) in online.items()}
    paths = snapshot_files(args.run_dir)
    if args.frames:
        paths = [path for path in paths if path.name in {SNAPSHOT_FILE.format(frames=f) for f in args.frames}]
    start = time.perf_counter()
    fixed = fixed_metrics(paths, inputs, args.layers, "cpu", 256, progress=True)
    seconds = time.perf_counter() - start
    lines = [
        f"snapshots of {args.run_dir} on {inputs.describe()} ({len(paths)} snapshots in {seconds:.0f} s)",
        "",
        "| frame | eval return | train-time mlp1 grad norm | action std | action saturation | layer | "
        + " | ".join(CORRELATION_READINGS)
        + " | dead units |",
        "|---|---|---|---|---|---|" + "---|" * (len(CORRELATION_READINGS) + 1),
    ]
    frames = fixed.metrics[metric_tag(args.layers[0], "dead_units")][0].tolist()
    for i, frame in enumerate(frames):
        ret = returns.get(frame, math.nan)
        grad = online_at.get(online_tags[0], {}).get(frame, math.nan)
        spread = online_at.get(online_tags[1], {}).get(frame, math.nan)
        saturation = online_at.get(online_tags[2], {}).get(frame, math.nan)
        for layer in args.layers:
            cells = " | ".join(_fmt(fixed.metrics[metric_tag(layer, r)][1][i]) for r in CORRELATION_READINGS)
            dead = int(fixed.metrics[metric_tag(layer, "dead_units")][1][i])
            lines.append(
                f"| {frame:,} | {ret:.1f} | {grad:.3g} | {_fmt(spread)} | {_fmt(saturation)} | {layer} | {cells} | "
                f"{dead} of {fixed.widths[layer]} |"
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=2048, help="inputs per layer (snapshots: 0 = all)")
    parser.add_argument("--width", type=int, default=1024, help="constructed layers' units")
    parser.add_argument("--dim", type=int, default=50, help="constructed layers' input dimension")
    parser.add_argument("--eps", type=float, default=0.05, help="size of the variation around the point")
    parser.add_argument("--bias-std", type=float, default=1.0, help="std of the biases of the 'bias' layers")
    parser.add_argument("--directions", type=int, nargs="+", default=[1, 3, 50], help="directions of the variation")
    parser.add_argument("--run-dir", help="a train run folder with --snapshots")
    parser.add_argument("--rollouts", help="rollouts file (probe record) of the fixed set")
    parser.add_argument("--layers", nargs="+", default=["mlp1", "mlp2"], help="snapshot layers")
    parser.add_argument("--frames", type=int, nargs="+", help="only the snapshots of these frames (default: all)")
    parser.add_argument("--train-episodes", action="store_true", help="the probe's training episodes (Figure 1's H)")
    parser.add_argument("--skip-constructed", action="store_true", help="snapshots only")
    args = parser.parse_args()
    th.set_num_threads(1)
    if not args.skip_constructed:
        print("\n".join(constructed_table(args)), flush=True)
    if args.run_dir:
        if not args.rollouts:
            parser.error("--run-dir needs --rollouts")
        print("\n" + "\n".join(snapshot_table(args)))


if __name__ == "__main__":
    main()
