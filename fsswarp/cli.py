"""The ``fsswarp`` command line (DESIGN §12).

Exit status: 0 done; 2 bad input (one line on stderr naming the file, field and value);
1 an internal error. Each command is one function below; shared options live in ``State``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import click

from .errors import InputError


@dataclass
class State:
    """Options shared by every command."""

    backend: str = "auto"
    device: str | None = None
    quiet: bool = False

    def echo(self, text: str = "") -> None:
        """Progress and summaries on stdout, unless --quiet."""
        if not self.quiet:
            click.echo(text)

    def get_backend(self):
        """The kernel backend the global options ask for (InputError if missing)."""
        from .backends import get_backend

        return get_backend(self.backend, self.device)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--backend", type=click.Choice(["auto", "warp", "opencl"]), default="auto", show_default=True,
              help="Kernel backend: 'auto' takes Warp on CUDA when a GPU is present, else OpenCL "
                   "(PoCL on CPU), else Warp on CPU.")
@click.option("--device", default=None,
              help="Device for the backend: Warp 'cpu', 'cuda' or 'cuda:N'; OpenCL a platform/device "
                   "name fragment (e.g. 'pocl', 'nvidia') or an index. See 'fsswarp info'.")
@click.option("--quiet", "-q", is_flag=True, help="Print no progress or summaries.")
@click.version_option(package_name="fsswarp")
@click.pass_context
def app(ctx: click.Context, backend: str, device: str | None, quiet: bool) -> None:
    """Forward-scan sonar engine: synthesize multipath (object, ghost, mirror) views, carve and
    refine 3-D models, estimate sonar depth and tilt, remove ghosts."""
    ctx.obj = State(backend=backend, device=device, quiet=quiet)


@app.command()
@click.pass_obj
def info(state: State) -> None:
    """List the kernel backends and devices found, which one 'auto' picks, and how to install
    what is missing. With --backend/--device, also check that choice."""
    from .backends import describe_backends

    chosen = state.get_backend() if state.backend != "auto" or state.device is not None else None
    click.echo(format_backends(describe_backends()))
    if chosen is not None:
        click.echo(f"selected: {chosen.name} on {chosen.device}")


@app.command()
@click.argument("path", type=click.Path(path_type=Path))
@click.pass_obj
def check(state: State, path: Path) -> None:
    """Validate a dataset folder (with dataset.toml) or a scene file (.toml) and summarize it.
    Exit 2 naming the first bad field."""
    from .dataset import load_dataset, load_scene

    if path.is_dir():
        dataset = load_dataset(path)
        manifest = dataset.manifest
        kind = f"dataset, {len(dataset.images)} images"
    elif path.is_file():
        manifest = load_scene(path)
        kind = "scene"
    else:
        raise InputError("no such file or folder", field="PATH", value=str(path))
    state.echo(f"{path}: valid {kind}")
    state.echo(describe_manifest(manifest))


@app.command()
@click.argument("name")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Scene file to write (.toml).")
@click.pass_obj
def scene(state: State, name: str, out: Path) -> None:
    """Write the built-in scene NAME (coral-one, coral-two or table) as a scene file, to edit
    and simulate."""
    from .dataset import save_scene
    from .scenes import builtin_scene

    if out.suffix != ".toml":
        raise InputError("must name a .toml file", field="--out", value=str(out))
    manifest = builtin_scene(name)
    save_scene(manifest, out)
    state.echo(f"wrote {out}: {name}, {len(manifest.rig.views)} views")


def describe_manifest(manifest) -> str:
    """A few lines that summarize a manifest for people."""
    sonar, surface, rig = manifest.sonar, manifest.surface, manifest.rig
    lines = [
        f"  sonar: {sonar.beams} beams x {sonar.bins} bins, azimuth {math.degrees(sonar.azimuth_fov):.4g} deg, "
        f"elevation {math.degrees(sonar.elevation_fov):.4g} deg, range {sonar.range_min:g}-{sonar.range_max:g} m"
        + (", beam angle table" if sonar.beam_angles is not None else ""),
        f"  surface (measured): depth {surface.depth:.4g} m +/- {surface.depth_sigma:.3g}, "
        f"tilt {math.degrees(surface.tilt):.4g} deg +/- {math.degrees(surface.tilt_sigma):.3g}",
    ]
    if manifest.truth is not None:
        lines.append(f"  truth: depth {manifest.truth.depth:.4g} m, tilt {math.degrees(manifest.truth.tilt):.4g} deg")
    if manifest.target is not None:
        target = manifest.target
        lines.append(f"  target: {target.builtin or target.mesh} at "
                     f"({', '.join(f'{v:.3g}' for v in target.position)}) m, scale {target.scale:g}")
    held = [v.name for v in rig.views if not v.optimize]
    lines.append(f"  views: {len(rig.views)} (reference {rig.views[rig.reference].name}; "
                 f"held out: {', '.join(held) if held else 'none'})")
    return "\n".join(lines)


def format_backends(rows: list[dict]) -> str:
    """The text of ``fsswarp info`` from ``describe_backends()`` rows."""
    lines = []
    for backend in ("warp", "opencl"):
        lines.append(f"{backend}:")
        for row in (r for r in rows if r["backend"] == backend):
            if not row["available"]:
                lines.append(f"  - {row['device']}: not available: {row['note']}")
                continue
            size = f", {row['memory_bytes'] / 2**30:.1f} GiB" if row["memory_bytes"] else ""
            units = f", {row['compute_units']} compute units" if row["compute_units"] else ""
            index = f"[{row['index']}] " if row["index"] is not None else ""
            version = f", {row['version']}" if row["version"] else f", {row['platform']}"
            lines.append(f"  - {index}{row['device']} ({row['kind']}{units}{size}{version})"
                         + ("  <- auto" if row["auto"] else ""))
    picked = [r for r in rows if r["auto"]]
    lines.append("auto picks: " + (f"{picked[0]['backend']} on {picked[0]['device']}" if picked else "nothing"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    try:
        app.main(args=argv, prog_name="fsswarp", standalone_mode=False)
    except InputError as err:
        print(f"fsswarp: error: {err}", file=sys.stderr)
        return 2
    except click.exceptions.NoArgsIsHelpError as err:
        click.echo(err.ctx.get_help())
        return 2
    except click.UsageError as err:
        command = err.ctx.command_path if err.ctx is not None else "fsswarp"
        message = " ".join(err.format_message().split())
        print(f"fsswarp: error: {message} (see '{command} --help')", file=sys.stderr)
        return 2
    except click.exceptions.Exit as done:
        return done.exit_code
    except (click.Abort, KeyboardInterrupt):
        print("fsswarp: interrupted", file=sys.stderr)
        return 130
    return 0
