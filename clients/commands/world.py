"""``vloc world``: generate a synthetic world as a data set folder."""

from __future__ import annotations

from pathlib import Path

import click


def _passes(value: str) -> list[str]:
    from vloc.clients.world import ILLUMINATIONS

    items = [v.strip() for v in value.split(",") if v.strip()]
    bad = [v for v in items if v not in ILLUMINATIONS]
    if bad or not items:
        raise click.BadParameter(f"unknown illumination {', '.join(bad) or '(none)'}; "
                                 f"valid: {', '.join(sorted(ILLUMINATIONS))}",
                                 param_hint="--passes")
    return items


@click.command("world")
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--kind", type=click.Choice(["robot", "uav"]), default="robot", show_default=True,
              help="Street block round which a ground robot drives (Weiss et al.), or open "
                   "land a quadcopter surveys (Flyphone).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Everything is drawn from this seed; the same arguments give the same bytes.")
@click.option("--passes", "passes_text", default="sunny,cloudy,dusk", show_default=True,
              help="Comma-separated illumination of each traversal (pass 1 is the map pass).")
@click.option("--frames", type=click.IntRange(2), default=None,
              help="Frames per pass. Alone it shortens the route to frames x spacing "
                   "(0.6 m robot, 3 m UAV); with --route-length it sets the stride.")
@click.option("--route-length", type=click.FloatRange(min=1.0), default=None,
              help="Route length in metres [default: 260 robot, 600 UAV].")
@click.option("--gps-noise", type=click.FloatRange(min=0.0), default=None,
              help="Sigma (m) of the GPS noise in the map pass's EXIF [default: 0.5 robot, 2 UAV].")
@click.option("--quality", type=click.IntRange(1, 100), default=90, show_default=True,
              help="JPEG quality.")
@click.option("--altitude", type=click.FloatRange(5.0, 100.0), default=None,
              help="UAV flight altitude in metres [default: 25].")
@click.option("--pitch", type=click.FloatRange(-90.0, 0.0), default=None,
              help="UAV camera pitch in degrees: -90 looks down (survey), 0 ahead (loop) "
                   "[default: -90].")
@click.option("--relief", type=click.FloatRange(0.0, 200.0), default=0.0,
              help="UAV only: hills this high (m, valley to hilltop) [default: 0, flat].")
@click.option("--altitude-drift", type=click.FloatRange(-1000.0, 1000.0), default=0.0,
              help="EXIF altitudes drift from the truth by this much (m) over each pass, "
                   "as a consumer GPS's does [default: 0].")
@click.option("--overwrite", is_flag=True, help="Replace the images of an earlier world in OUT.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def world_cmd(out: Path, kind: str, seed: int, passes_text: str, frames, route_length,
              gps_noise, quality: int, altitude, pitch, relief: float, altitude_drift: float,
              overwrite: bool, quiet: bool) -> None:
    """Generate a synthetic world: a route rendered under several illuminations.

    Writes OUT/images/*.jpg (320x240, EXIF GPS and capture time), OUT/ground_truth.csv
    (filename,pass,captured_at,lat,lon,alt_m: true positions), OUT/exif_gps.csv,
    OUT/poses.csv and OUT/world.json. Pass 1 is the map pass: its EXIF carries the true
    position plus the GPS noise; the other passes carry the true position.
    """
    from vloc.clients.world import generate_world

    passes = _passes(passes_text)
    if kind == "robot" and (altitude is not None or pitch is not None or relief):
        raise click.BadParameter("--altitude, --pitch and --relief apply to --kind uav only")
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(total=0, unit="frame", desc="rendering", leave=False)

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()

    try:
        info = generate_world(out, kind=kind, seed=seed, passes=passes, frames=frames,
                              route_length=route_length, gps_noise_m=gps_noise,
                              quality=quality, altitude=altitude, pitch_deg=pitch,
                              relief_m=relief, altitude_drift_m=altitude_drift,
                              overwrite=overwrite, progress=progress)
    except (ValueError, FileExistsError) as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        if bar is not None:
            bar.close()
    seconds = sum(info.timings.values())
    click.echo(f"{info.images} images in {info.out_dir}: {info.kind}, seed {info.seed}, "
               f"{len(info.passes)} passes ({', '.join(info.passes)}) of "
               f"{info.frames_per_pass} frames, route {info.route_length_m:.0f} m, "
               f"{info.frame_spacing_m:.2f} m between frames, GPS noise {info.gps_noise_m:g} m "
               f"on pass 1; {seconds:.1f} s")
