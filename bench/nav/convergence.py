"""Path following on the robot world's taught route: the control law and the EKF in closed
loop with a simulated robot, localisation modelled as noisy pose fixes.

Li et al.'s Fig. 13 experiment: starts 1 m to the side of the taught path and 20 degrees
off its heading, at random places along it; a start succeeds when the robot comes within
0.3 m and 10 degrees of the path within 5 m of travel and stays within 0.3 m. Also one
repeat of the whole route from its start, for the mean cross-track error. The robot is Li's
unicycle (eq. 6) with actuation noise (5 % of v and omega, 0.01 rad/s slip); each frame
(one a second at 0.6 m/s) gives a fix of position and heading with Gaussian noise.
Localisation through the service on rendered frames is measured by ``vloc navigate``.

    .venv/bin/python bench/nav/convergence.py [--starts 40] [--seed 0] [--sigma 0.25] [--alpha 1] [--dt 0.5]

Writes bench/results/nav_convergence.md, .json and .png.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path as FilePath

import numpy as np

sys.path.insert(0, str(FilePath(__file__).resolve().parents[2]))  # the repository

from bench._common import RESULTS, write_result  # noqa: E402
from vloc.clients.world import robot  # noqa: E402
from vloc.clients.world.routes import rounded_rectangle  # noqa: E402
from vloc.workers.core.navigation import (  # noqa: E402
    ActuationNoise,
    FollowerConfig,
    Path,
    PathFollower,
    unicycle_step,
)

SUBSTEPS = 10


def taught_path(seed: int, length: float) -> np.ndarray:
    """The true camera positions of a taught drive round a block of the robot world."""
    rng = np.random.default_rng(seed)
    block = robot.block_for(length, rng)
    route = rounded_rectangle(block.half_x, block.half_y, block.radius)
    poses = robot.robot_poses(route, rng, frames=int(length / robot.SPACING),
                              spacing=robot.SPACING)
    return np.array([[p.position[0], p.position[1], p.yaw] for p in poses])


def drive(path: Path, start: np.ndarray, rng: np.random.Generator, *, sigma: float,
          sigma_heading: float, max_travel: float, config: FollowerConfig) -> dict:
    follower = PathFollower(path, [0.0], config)
    noise = ActuationNoise()
    pose = start.copy()
    travel, s_hint, rows = 0.0, None, []
    for _ in range(int(max_travel / (0.5 * config.control.v_max * config.dt)) + 50):
        z = pose[:2] + rng.normal(0.0, sigma, 2)
        h = pose[2] + rng.normal(0.0, sigma_heading)
        st = follower.step(z, np.eye(2) * sigma ** 2, heading=h, heading_sigma=sigma_heading)
        p = path.project(pose[:2], s_hint=s_hint)
        s_hint = p.s
        rows.append((travel, p.d, math.remainder(pose[2] - p.theta, 2 * math.pi), *pose))
        if st.arrived or travel >= max_travel:
            break
        v, w = noise.apply(*st.command, rng)
        for _ in range(SUBSTEPS):
            pose = unicycle_step(pose, v, w, config.dt / SUBSTEPS)
        travel += abs(v) * config.dt
    a = np.array(rows)
    return {"travel": a[:, 0], "d": a[:, 1], "heading": a[:, 2], "xy": a[:, 3:5]}


def converged_at(run: dict) -> float | None:
    d, h = np.abs(run["d"]), np.abs(run["heading"])
    for k in range(len(d)):
        if d[k] < 0.3 and h[k] < math.radians(10) and (d[k:] < 0.3).all():
            return float(run["travel"][k])
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--length", type=float, default=260.0)
    ap.add_argument("--sigma", type=float, default=0.25, help="fix position sigma, m")
    ap.add_argument("--sigma-heading", type=float, default=5.0, help="fix heading sigma, deg")
    ap.add_argument("--alpha", type=float, default=1.0, help="k2 = alpha^2, k3 = 2 xi alpha")
    ap.add_argument("--dt", type=float, default=0.5, help="seconds between frames")
    ap.add_argument("--out", type=FilePath, default=RESULTS / "nav_convergence")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    taught = taught_path(args.seed, args.length)
    path = Path(taught[:, :2], smoothing=1.0)
    config = FollowerConfig.from_params({"alpha": args.alpha, "dt": args.dt})
    sh = math.radians(args.sigma_heading)
    full = drive(path, taught[0].copy(), rng, sigma=args.sigma, sigma_heading=sh,
                 max_travel=1.5 * path.length, config=config)
    truth = Path(taught[:, :2], smoothing=0.0)
    s_hint, d_true = None, []
    for xy in full["xy"]:
        p = truth.project(xy, s_hint=s_hint)
        s_hint = p.s
        d_true.append(abs(p.d))
    starts = []
    for _ in range(args.starts):
        k = int(rng.integers(0, len(taught) - 40))
        side, turn = rng.choice([-1.0, 1.0]), rng.choice([-1.0, 1.0])
        x, y, th = taught[k]
        start = np.array([x - side * math.sin(th), y + side * math.cos(th),
                          th + turn * math.radians(20.0)])
        run = drive(path, start, rng, sigma=args.sigma, sigma_heading=sh, max_travel=15.0,
                    config=config)
        starts.append({"image": k, "side_m": side, "heading_deg": 20.0 * turn,
                       "converged_at_m": converged_at(run), "_run": run})
    ok = [s for s in starts if s["converged_at_m"] is not None and s["converged_at_m"] <= 5.0]
    conv = [s["converged_at_m"] for s in starts if s["converged_at_m"] is not None]
    summary = {
        "route_m": path.length, "fix_sigma_m": args.sigma, "fix_sigma_heading_deg":
        args.sigma_heading, "control": config.to_params(),
        "full_route": {"mean_cross_track_m": float(np.mean(np.abs(full["d"]))),
                       "max_cross_track_m": float(np.max(np.abs(full["d"]))),
                       "mean_cross_track_true_path_m": float(np.mean(d_true)),
                       "travel_m": float(full["travel"][-1])},
        "starts": {"n": len(starts), "success_within_5m": len(ok),
                   "success_rate": len(ok) / len(starts),
                   "median_converged_at_m": float(np.median(conv)) if conv else None,
                   "runs": [{k: v for k, v in s.items() if k != "_run"} for s in starts]}}
    print(json.dumps({k: v for k, v in summary.items() if k != "starts"}, indent=1))
    print(f"starts: {len(ok)}/{len(starts)} converged within 5 m; median "
          f"{summary['starts']['median_converged_at_m']}")
    write(args, summary, full, starts)


def write(args, summary: dict, full: dict, starts: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    st, fr = summary["starts"], summary["full_route"]
    cmd = (f".venv/bin/python bench/nav/convergence.py --starts {args.starts} --seed {args.seed} "
           f"--length {args.length:g} --sigma {args.sigma:g} --sigma-heading {args.sigma_heading:g} "
           f"--alpha {args.alpha:g} --dt {args.dt:g}")
    lines = ["# Path following on the robot world's taught route (Li et al. eq. 8 with the EKF)",
             "", f"Command: `{cmd}`", "",
             "Localisation modelled as pose fixes with Gaussian noise (position "
             f"{args.sigma:g} m per axis, heading {args.sigma_heading:g} deg), one every "
             f"{args.dt:g} s at 0.6 m/s; unicycle with 5 % actuation noise; alpha = {summary['control']['alpha']}"
             ", xi = 1/sqrt(2). Through the service on rendered frames see `vloc navigate` "
             "(README).", "",
             f"- whole route ({summary['route_m']:.0f} m) from its start: mean cross-track error "
             f"{fr['mean_cross_track_m']:.3f} m (max {fr['max_cross_track_m']:.2f} m)",
             f"- {st['n']} random starts 1 m to the side and 20 deg off: {st['success_within_5m']}"
             f"/{st['n']} converged within 5 m of travel (success rate "
             f"{100 * st['success_rate']:.0f} %), median {st['median_converged_at_m']:.1f} m", "",
             "| start image | side (m) | heading (deg) | converged after (m) |",
             "|---:|---:|---:|---:|"]
    for s in st["runs"]:
        c = s["converged_at_m"]
        lines.append(f"| {s['image']} | {s['side_m']:+.0f} | {s['heading_deg']:+.0f} | "
                     f"{'never' if c is None else f'{c:.1f}'} |")
    md = write_result(args.out.with_suffix(".md"), "\n".join(lines) + "\n", echo=False)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    for s in starts:
        ax1.plot(s["_run"]["travel"], s["_run"]["d"], lw=0.8)
    ax1.axhline(0.3, color="grey", ls="--", lw=0.5)
    ax1.axhline(-0.3, color="grey", ls="--", lw=0.5)
    ax1.axvline(5.0, color="k", ls=":", lw=0.8)
    ax1.set_xlabel("travelled (m)")
    ax1.set_ylabel("cross-track error (m)")
    ax1.set_title(f"{st['success_within_5m']}/{st['n']} starts converge within 5 m")
    ax2.plot(full["travel"], full["d"], lw=0.8)
    ax2.set_xlabel("travelled (m)")
    ax2.set_ylabel("cross-track error (m)")
    ax2.set_title(f"whole route: mean |d| {fr['mean_cross_track_m']:.3f} m")
    fig.tight_layout()
    fig.savefig(args.out.with_suffix(".png"), dpi=110)
    print(f"wrote {md}")


if __name__ == "__main__":
    main()
