"""The ``fsswarp`` command line (DESIGN §12).

Exit status: 0 done; 2 bad input (one line on stderr naming the file, field and value);
1 an internal error; 130 interrupted (Ctrl-C: one line, no output folder). A command checks
all of its input before it prints anything. Each command is one function below; shared
options live in ``State``. The JSON files and meshes come from ``fsswarp.outputs``, the
figures from ``fsswarp.figures``.
"""

from __future__ import annotations

import json
import math
import sys
import warnings
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import click

from .errors import InputError

#: The file that marks each command's output folder: ``fsswarp.atomic.output_folder`` replaces
#: an existing --out only if it holds this file (or is empty).
MARKERS = {"bench": "bench.json", "render": "render.json", "carve": "carve.json", "demo": "demo.json",
           "reconstruct": "result.json", "enhance": "enhance.json", "pose": "pose.json"}


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

    def start_mesh_workers(self) -> None:
        """Start the processes that mesh carvings (``fsswarp.carving.start_mesh_workers``) now,
        before the backend: their imports (~1 s each) then overlap the command's input and
        simulation instead of the loop's start; they stop when Python exits."""
        from .carving import start_mesh_workers

        start_mesh_workers()

    def figure_drawer(self):
        """A ``fsswarp.figures.FigureDrawer`` whose processes start now (call it once the
        command's input is checked) and stop when the command ends."""
        from .figures import FigureDrawer

        drawer = FigureDrawer()
        click.get_current_context().call_on_close(drawer.close)
        return drawer


class CommandLine(click.Group):
    """The ``fsswarp`` group: Ctrl-C ends a command as ``click.Abort``, which ``main`` reports
    in one line (click would print a blank line before it)."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            raise click.Abort() from None


@click.group(cls=CommandLine, context_settings={"help_option_names": ["-h", "--help"]})
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


def start_options(command):
    """--depth and --tilt, the start of reconstruct's and pose's searches."""
    command = click.option("--tilt", type=float, default=None,
                           help="Initial sonar tilt (deg); default: the dataset's measured tilt.")(command)
    return click.option("--depth", type=float, default=None,
                        help="Initial sonar depth D0 (m); default: the dataset's measured depth.")(command)


@app.command()
@click.option("--warm-up", "warm", is_flag=True,
              help="First compile the kernels that the chosen backend's cache lacks (Warp: its modules side by side; "
                   "OpenCL: its programs, built as the backend is made), so that no later run compiles them.")
@click.pass_obj
def info(state: State, warm: bool) -> None:
    """List the kernel backends and devices found, which one 'auto' picks, how to install what
    is missing, and whether each device's kernel cache holds fsswarp's kernels (warm: no
    compilation on the first run). With --backend/--device, also check that choice."""
    import time

    from .backends import describe_backends
    from .backends.cache import kernel_cache, warm_up

    chosen = None
    if warm or state.backend != "auto" or state.device is not None:
        start = time.perf_counter()
        chosen = state.get_backend()
        if warm:
            made = time.perf_counter() - start
            compiled, seconds = warm_up(chosen)
            if chosen.name == "opencl":
                click.echo(f"warm-up of opencl on {chosen.device}: its programs built (or loaded from the driver's "
                           f"cache) as the backend was made, in {made:.1f} s")
            else:
                what = f"compiled {', '.join(compiled)}" if compiled else "every module loaded from the cache"
                click.echo(f"warm-up of {chosen.name} on {chosen.device}: {what} in {seconds:.1f} s")
    rows = describe_backends()
    click.echo(format_backends(rows))
    click.echo("kernel cache (checked without compiling; docs/benchmarks.md):")
    for row in (r for r in rows if r["available"]):
        warm, why = kernel_cache(row)
        index = f"[{row['index']}] " if row["index"] is not None else ""
        click.echo(f"  - {row['backend']} {index}{row['device']}: {warm} ({why})")
    if chosen is not None:
        click.echo(f"selected: {chosen.name} on {chosen.device}")


@app.command()
@click.option("--out", default=Path("bench-out"), show_default=True, type=click.Path(path_type=Path),
              help="Folder for bench.json, bench.md and one plot per family (<family>.png).")
@click.option("--quick", is_flag=True, help="Tiny sizes: checks that every family runs, in about a minute.")
@click.option("--families", default=",".join(("raycast", "synthesis", "carving", "pose", "reconstruction")),
              show_default=True, help="Comma-separated families to run.")
@click.option("--budget", default=20.0, show_default=True, type=float,
              help="Seconds per point: a point projected to take longer is skipped, and so are larger ones.")
@click.option("--repeat", default=3, show_default=True, type=click.IntRange(min=1),
              help="Timed runs per figure after a warm-up (the median is reported, with min and max).")
@click.option("--no-peers", is_flag=True, help="Leave out Embree, the NumPy reference and CuPy.")
@click.pass_obj
def bench(state: State, out: Path, quick: bool, families: str, budget: float, repeat: int, no_peers: bool) -> None:
    """Benchmark the kernels (ray casting, synthesis, carving, pose grid, reconstruction) on
    every backend present, or the one --backend/--device selects, with peers, each figure
    beside its physical limit: OUT/bench.json, OUT/bench.md and OUT/<family>.png."""
    import time

    from . import benchmark as suite
    from .atomic import check_output_folder, output_folder
    from .backends import describe_backends, get_backend

    chosen = [f.strip() for f in families.split(",") if f.strip()]
    suite.check_options(chosen, budget)
    check_output_folder(out, marker=MARKERS["bench"])
    if state.backend != "auto" or state.device is not None:
        backends = [state.get_backend()]
    else:
        rows = [r for r in describe_backends() if r["available"]]
        backends = [get_backend(r["backend"], r["device"] if r["backend"] == "warp" else r["index"]) for r in rows]
    selection = "".join(f" --{k} {v!r}" if " " in str(v) else f" --{k} {v}"
                        for k, v in (("backend", state.backend), ("device", state.device))
                        if v not in (None, "auto"))
    command = (f"fsswarp{selection} bench --out {out}{' --quick' if quick else ''} --families {','.join(chosen)} "
               f"--budget {budget:g} --repeat {repeat}{' --no-peers' if no_peers else ''}")
    start = time.perf_counter()
    state.echo(f"benchmarking {', '.join(chosen)} on " + "; ".join(f"{b.name} {b.device}" for b in backends))
    run = suite.run_suite(backends, chosen, quick=quick, budget=budget, repeat=repeat, peers=not no_peers,
                          command=command, progress=state.echo)
    run["seconds"] = time.perf_counter() - start
    with output_folder(out, marker=MARKERS["bench"]) as tmp:
        (tmp / "bench.json").write_text(json.dumps(run, indent=1))
        (tmp / "bench.md").write_text(f"# fsswarp bench\n\n{suite.machine_markdown(run)}\n{suite.markdown(run)}")
        plots = [suite.plot_family(run["records"], family, tmp / f"{family}.png") for family in chosen]
    state.echo(f"wrote {out}: bench.json, bench.md, {sum(p is not None for p in plots)} plots "
               f"({run['seconds']:.0f} s)")


@app.command()
@click.argument("path", type=click.Path(path_type=Path))
@click.pass_obj
def check(state: State, path: Path) -> None:
    """Validate a dataset folder (with dataset.toml) or a scene file (.toml) and summarize it.
    Exit 2 naming the first bad field."""
    from .dataset import load_dataset, load_scene
    from .scenes import target_world_mesh

    if path.is_dir():
        dataset = load_dataset(path)
        manifest = dataset.manifest
        truth = dataset.truth_mesh()
        layers = dataset.check_truth_layers()
        kind = (f"dataset, {len(dataset.images)} images" + (f", {layers} truth layers" if layers else "")
                + (f", truth model of {len(truth.faces)} triangles" if truth is not None else ""))
    elif path.is_file():
        manifest = load_scene(path)
        target_world_mesh(manifest.target, base=path.parent, file=path)  # read and placed as simulate will
        kind = "scene"
    elif path.exists():
        raise InputError("is neither a regular file nor a folder", field="PATH", value=str(path))
    else:
        raise InputError("no such file or folder", field="PATH", value=str(path))
    state.echo(f"{path}: valid {kind}")
    state.echo(describe_manifest(manifest))


@app.command()
@click.argument("name")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Scene file to write (.toml).")
@click.option("--positions", default=None,
              help="Sonar positions around the target, distinct letters of S, N, E, W (2 m) and T (south, 1.4 m), "
                   "eight rolls at each [default: the scene's own, SN for the corals, SNEW for the table].")
@click.option("--sensors", default="realistic", show_default=True, type=click.Choice(["realistic", "poor"]),
              help="The measured depth and tilt: 'realistic' (depth sigma 3 mm, within 3 mm of the truth; tilt "
                   "sigma 0.6 deg, 0.6-1 deg off) or 'poor' (depth sigma 5 cm, 3-5 cm off; tilt sigma 2 deg).")
@click.option("--deep-water", is_flag=True,
              help="The same rig and target 20 m deeper with no sea surface in view: no [surface] and no [truth] "
                   "table, the depth and tilt known ([rig] depth_m, tilt_deg); its images hold the object alone.")
@click.pass_obj
def scene(state: State, name: str, out: Path, positions: str | None, sensors: str, deep_water: bool) -> None:
    """Write the built-in scene NAME (coral-one, coral-two or table) as a scene file, to edit
    and simulate."""
    from .dataset import save_scene
    from .scenes import builtin_scene

    if out.suffix != ".toml":
        raise InputError("must name a .toml file", field="--out", value=str(out))
    manifest = builtin_scene(name, positions, sensors, deep_water=deep_water)
    save_scene(manifest, out)
    surface = manifest.surface
    if surface is None:
        state.echo(f"wrote {out}: {name}, {len(manifest.rig.views)} views, deep water (depth "
                   f"{manifest.known_pose.depth:g} m, tilt {math.degrees(manifest.known_pose.tilt):g} deg, known)")
        return
    state.echo(f"wrote {out}: {name}, {len(manifest.rig.views)} views, {sensors} sensors (depth "
               f"{surface.depth:g} +/- {surface.depth_sigma:g} m, tilt {math.degrees(surface.tilt):g} +/- "
               f"{math.degrees(surface.tilt_sigma):g} deg)")


@app.command()
@click.argument("scene_name", metavar="SCENE")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Dataset folder to write.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Noise seed.")
@click.option("--samples", nargs=2, type=int, default=(2, 64), show_default=True,
              help="Sub-rays per beam: K_theta across the beam, K_phi over the elevation aperture.")
@click.option("--no-noise", is_flag=True, help="Write the noise-free total as the images.")
@click.pass_obj
def simulate(state: State, scene_name: str, out: Path, seed: int, samples, no_noise: bool) -> None:
    """Synthesize a dataset of SCENE, a scene file or a built-in scene (coral-one, coral-two,
    table): noisy images plus the noise-free object, ghost, mirror and mirror2 layers and the
    truth model under truth/."""
    import time

    from .figures import draw_here
    from .rendering import RenderSettings
    from .simulation import simulate as run

    settings = RenderSettings(samples=tuple(samples))
    backend = state.get_backend()
    start = time.perf_counter()
    dataset = run(scene_name, out, seed=seed, settings=settings, noise=not no_noise, backend=backend)
    seconds = time.perf_counter() - start
    figure = simulation_figure(dataset, out / "figures" / "layers.png", draw_here)
    state.echo(f"wrote {out}: {len(dataset.images)} views of {scene_name} "
               f"({backend.name} on {backend.device}, {seconds:.2f} s); figure {figure}")


def simulation_figure(dataset, path: Path, draw) -> Path:
    """Layers and noisy data of up to three views (roll 0, the largest positive and the most
    negative roll of the reference position) as beam-bin and fan images, drawn by ``draw``
    (``fsswarp.figures.FigureDrawer.batch``); returns ``path``."""
    import numpy as np

    from .figures import layers_figure
    from .surface import COMPONENTS

    views = dataset.rig.views
    ref = views[dataset.rig.reference]
    same = [v for v in views if v.position == ref.position and v.heading == ref.heading]
    chosen = {min(same, key=lambda v: abs(v.roll)).name, max(same, key=lambda v: v.roll).name,
              min(same, key=lambda v: v.roll).name}
    components = ("object",) if dataset.manifest.deep_water else COMPONENTS  # deep water: no multipath layers
    stacks = {name: np.stack([dataset.truth_layer(name, c) for c in components] + [dataset.images[name]])
              for name in [v.name for v in same if v.name in chosen]}
    draw(layers_figure, stacks, dataset.sonar, path, layers=components + ("data",),
         title="simulated layers (noise-free) and data (noisy)")
    return path


@app.command()
@click.argument("model", type=click.Path(path_type=Path))
@click.option("--dataset", "dataset_dir", required=True, type=click.Path(path_type=Path),
              help="Dataset folder whose sonar and view poses to use.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Folder for the TIFF layers.")
@click.option("--depth", type=float, default=None, help="Sonar depth D (m); default: the dataset's measured depth.")
@click.option("--tilt", type=float, default=None, help="Sonar tilt (deg); default: the dataset's measured tilt.")
@click.option("--view", "view_names", multiple=True, help="Render only this view (repeatable).")
@click.option("--roll", "rolls", type=float, multiple=True,
              help="Also render a new view at this roll (deg), at the position and heading of the "
                   "--at view, named roll<DEG> (repeatable). With --roll alone only the new views render.")
@click.option("--at", "at_view", default=None, help="View whose position and heading --roll uses "
                                                    "(default: the reference view).")
@click.option("--samples", nargs=2, type=int, default=(2, 64), show_default=True,
              help="Sub-rays per beam: K_theta across the beam, K_phi over the elevation aperture.")
@click.pass_obj
def render(state: State, model: Path, dataset_dir: Path, out: Path, depth, tilt, view_names, rolls, at_view,
           samples) -> None:
    """Render synthetic views of the mesh MODEL (in the dataset's reference frame) at the
    dataset's poses or at new rolls: OUT/<view>_{total,object,ghost,mirror,mirror2}.tiff and
    OUT/layers.png (beam-bin and fan images of up to six views)."""

    from .atomic import check_output_folder, output_folder
    from .dataset import deep_water_pose, load_manifest, tiff_bytes
    from .figures import layers_figure
    from .rendering import LAYERS, RenderSettings, RenderWarning
    from .rendering import render as run
    from .rig import with_rolls

    manifest = load_manifest(dataset_dir)
    mesh = load_mesh_file(model)
    check_output_folder(out, marker=MARKERS["render"])
    deep = deep_water(manifest, depth, tilt)
    if deep:  # the surface beyond every range window: the object layer alone
        depth, tilt = deep_water_pose(manifest)
    else:
        depth = manifest.surface.depth if depth is None else depth
        tilt = manifest.surface.tilt if tilt is None else math.radians(tilt)
    settings = RenderSettings(samples=tuple(samples))
    rig, new_names = with_rolls(manifest.rig, [math.radians(r) for r in rolls], at=at_view)
    names = list(view_names) + new_names if (view_names or new_names) else None
    backend = state.get_backend()
    with warnings.catch_warnings():
        if deep:
            warnings.filterwarnings("ignore", "view .*: ghost returns reach", RenderWarning)
        views = run(mesh, manifest.sonar, rig, depth, tilt, views=names, settings=settings, backend=backend)
    with output_folder(out, marker=MARKERS["render"]) as tmp:
        images = {f"{name}_{layer}.tiff": image for name, stack in views.items() for layer, image in zip(LAYERS, stack)}
        for file, data in tiff_bytes(images).items():
            (tmp / file).write_bytes(data)
        shown = dict(list(views.items())[:6])
        layers_figure(shown, manifest.sonar, tmp / "layers.png",
                      title=f"{model.name}: D = {depth:.3f} m, tilt = {math.degrees(tilt):.2f} deg"
                            + (f" (first 6 of {len(views)} views)" if len(views) > 6 else ""))
        (tmp / "render.json").write_text(json.dumps({
            "model": str(model), "dataset": str(dataset_dir), "depth_m": depth, "tilt_deg": math.degrees(tilt),
            "views": list(views), "new_views": {v.name: {"roll_deg": math.degrees(v.roll), "at": at_view or
                                                         manifest.rig.views[manifest.rig.reference].name}
                                                for v in rig.views if v.name in new_names},
            "samples": list(samples), "backend": backend.name, "device": backend.device,
        }, indent=2))
    state.echo(f"wrote {out}: {len(views)} views x {len(LAYERS)} layers, figure {out / 'layers.png'}")


def deep_water(manifest, depth=None, tilt=None) -> bool:
    """Whether ``manifest`` is deep water (no [surface]: known depth and tilt); InputError when
    --depth or --tilt was given for one."""
    if manifest.surface is not None:
        return False
    if depth is not None or tilt is not None:
        raise InputError("the dataset has no sea surface (deep water): its depth and tilt are known ([rig] depth_m, "
                         "tilt_deg)", field="--depth" if depth is not None else "--tilt",
                         value=depth if depth is not None else tilt)
    return True


def load_mesh_file(path: Path, field: str = "MODEL"):
    """The mesh of the MODEL argument, or of the option ``field`` (``fsswarp.dataset.read_mesh``)."""
    from .dataset import read_mesh

    return read_mesh(path, field=field)


@app.command("import")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Dataset folder to write.")
@click.option("--frames", "frames_spec", default=None,
              help="Frames to import, 0-based positions in the file: 'all' (default) or a list like '0-3,5'.")
@click.option("--elevation-fov-deg", type=float, default=None,
              help="Full elevation aperture (deg); the files do not hold it. Default 14 (ARIS 1200/1800/3000 "
                   "standard lenses, unconfirmed for the ARIS telephoto lens; the DIDSON's 14 deg beam).")
@click.option("--poses", type=click.Path(path_type=Path), default=None,
              help="CSV of view poses: frame,x_m,y_m,heading_deg,roll_deg[,depth_offset_m,tilt_offset_deg]. "
                   "Default: every view at the origin, heading 0, roll 0.")
@click.option("--depth", type=float, default=None,
              help="Measured sonar depth D0 (m); default: the median of the frames' depth sensor values "
                   "(ARIS Depth, DIDSON depth; required when the recording has none).")
@click.option("--tilt", type=float, default=None,
              help="Measured sonar tilt (deg, positive = up); default: the median of the frames' tilt "
                   "sensor values (ARIS CompassPitch, DIDSON sonartilt).")
@click.option("--window-start", type=float, default=None,
              help="DIDSON only: the range of the first sample (m), replacing the one decoded from the "
                   "frame's start code.")
@click.option("--window-length", type=float, default=None,
              help="DIDSON only: the range window's length (m; 512 samples), replacing the one decoded "
                   "from the frame's length code.")
@click.pass_obj
def import_command(state: State, file: Path, out: Path, frames_spec, elevation_fov_deg, poses, depth, tilt,
                   window_start, window_length) -> None:
    """Import a Sound Metrics recording, ARIS (.aris) or DIDSON (.ddf, versions 3 and 4, told
    apart by their first bytes), as a dataset: one view per frame (f0000, f0001, ...), the
    lens's beam angles, the sensors' depth and tilt as the measured D0 and tilt, OUT/source.json
    (format, header values used, the options given; ARIS also aris.json) and
    figures/frame0_fan.png (the first imported frame). 'import-aris' is another name for it.
    FILE may also be a HoloOcean-style folder (Config.json and Data/*.pkl, as 'fsswarp export'
    writes and NeuSIS reads), which takes no options."""
    from .figures import fan_figure
    from .importing import SOURCE_RECORD, import_recording

    dataset = import_recording(file, out, frames=frames_spec, elevation_fov_deg=elevation_fov_deg, poses=poses,
                               depth_m=depth, tilt_deg=tilt, window_start_m=window_start,
                               window_length_m=window_length)
    source = json.loads((out / SOURCE_RECORD).read_text())
    record = source["header_values"]
    first = dataset.rig.views[0].name
    if source["format"] == "HoloOcean":  # fsswarp.holoocean
        figure = fan_figure(dataset.images[first], dataset.sonar, out / "figures" / "frame0_fan.png",
                            title=f"{file.name} {first} (HoloOcean)")
        at = record["poses_at"]
        state.echo(f"wrote {out}: {len(dataset.images)} views of {file} (HoloOcean, {dataset.sonar.beams} azimuth x "
                   f"{dataset.sonar.bins} range bins); figure {figure}")
        state.echo(f"  {'deep water (no sea surface); ' if record['deep_water'] else ''}poses about depth "
                   f"{at['depth_m']:.4g} m, tilt {at['tilt_deg']:.4g} deg ({at['source']})"
                   + ("; truth model from gt.ply" if record["truth_model"] else ""))
        return
    if source["format"] == "ARIS":
        kind = f"{record['system']}, {record['lens']} lens"
    else:
        kind = f"DIDSON v{source['version']}, {record['configuration']}, {record['frequency']} frequency"
    figure = fan_figure(dataset.images[first], dataset.sonar, out / "figures" / "frame0_fan.png",
                        title=f"{file.name} {first} ({kind})")
    state.echo(f"wrote {out}: {len(dataset.images)} views of {file} ({kind}, {record['beams']} beams x "
               f"{record['samples_per_beam']} samples); figure {figure}")
    if source["format"] == "ARIS":
        frame0 = record["frames"][0]
        state.echo(f"  range {dataset.sonar.range_min:.4g}-{dataset.sonar.range_max:.4g} m computed; window start "
                   f"{frame0['window_start_m']:.4g} m, length {frame0['window_length_m']:.4g} m "
                   f"(stored {frame0['window_start_m_stored']:.4g} m, {frame0['window_length_m_stored']:.4g} m)")
    else:
        window = record["window"]
        state.echo(f"  range {dataset.sonar.range_min:.4g}-{dataset.sonar.range_max:.4g} m; window start "
                   f"{window['start_m']:.4g} m ({window['start_source']}, code {window['start_code']}), length "
                   f"{window['length_m']:.4g} m ({window['length_source']}, code {window['length_code']})")
    surface = record["surface"]
    state.echo(f"  measured depth {surface['depth_m']:.4g} m ({surface['depth_source']}), tilt "
               f"{surface['tilt_deg']:.4g} deg ({surface['tilt_source']}); elevation "
               f"{record['elevation_fov_deg']:g} deg ({record['elevation_source']})")


app.add_command(import_command, "import-aris")


@app.command()
@click.argument("dataset_dir", metavar="DIR", type=click.Path(path_type=Path))
@click.option("--format", "form", type=click.Choice(["holoocean"]), default="holoocean", show_default=True,
              help="The layout to write: holoocean, the HoloOcean-style folder that NeuSIS and SonarSplat read.")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for Config.json, Data/000000.pkl, ... (one per view) and gt.ply (the truth model).")
@click.pass_obj
def export(state: State, dataset_dir: Path, form: str, out: Path) -> None:
    """Write the dataset DIR in another tool's layout. holoocean: OUT/Config.json (the
    ImagingSonar's configuration), OUT/Data/000000.pkl, ... (per view the image, scaled to
    [0, 1], and the PoseSensor, its 4 x 4 sensor-to-world pose in HoloOcean's frame) and, for
    simulated data, OUT/gt.ply (the truth model in the world frame). 'fsswarp import OUT'
    reads it back."""
    from .dataset import load_dataset
    from .holoocean import CONFIG, TRUTH_FILE, export_holoocean

    dataset = load_dataset(dataset_dir)
    export_holoocean(dataset, out)
    table = json.loads((out / CONFIG).read_text())["fsswarp"]
    at = table["poses_at"]
    state.echo(f"wrote {out}: {CONFIG}, Data/ ({len(dataset.images)} views)"
               + (f", {TRUTH_FILE}" if (out / TRUTH_FILE).is_file() else ""))
    state.echo(f"  poses at the {at['source']} depth {at['depth_m']:.4g} m and tilt {at['tilt_deg']:.4g} deg; images "
               f"divided by {table['intensity_scale']:.6g}"
               + ("; the beam-angle table resampled to uniform azimuth bins" if table["azimuth_resampled"] else ""))


@app.command()
@click.argument("dataset_dir", metavar="DIR", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for carved.ply, carve.json and carve.png.")
@click.option("--depth", type=float, default=None, help="Sonar depth D (m); default: the dataset's measured depth.")
@click.option("--tilt", type=float, default=None, help="Sonar tilt (deg); default: the dataset's measured tilt.")
@click.option("--resolution", default=128, show_default=True, type=click.IntRange(8, 1024),
              help="Voxels along the longest side of the carving box at the finest level.")
@click.option("--box", nargs=6, type=float, default=None, metavar="X0 Y0 Z0 X1 Y1 Z1",
              help="Carve only inside this box (reference frame, m); default: the region every view sees.")
@click.option("--faces", default=20_000, show_default=True, type=click.IntRange(min=0),
              help="Decimate the mesh to at most this many triangles (0: keep all); the decimation moves the "
                   "surface by at most 2 voxels and warns where that leaves more.")
@click.pass_obj
def carve(state: State, dataset_dir: Path, out: Path, depth, tilt, resolution: int, box, faces: int) -> None:
    """Segment every view and carve the voxels they agree on into a closed mesh (space carving):
    OUT/carved.ply (reference frame), OUT/carve.json (grid, voxels kept, timings, and metrics
    against truth/model.ply when the dataset has one) and OUT/carve.png."""
    import dataclasses
    import time

    import numpy as np

    from .atomic import check_output_folder, output_folder
    from .carving import CarveSettings, check_box
    from .carving import carve as run
    from .dataset import load_dataset
    from .figures import carve_figure
    from .outputs import carve_record, write_carve
    from .errors import check_depth_tilt

    start = time.perf_counter()
    dataset = load_dataset(dataset_dir)
    loaded = time.perf_counter() - start
    check_output_folder(out, marker=MARKERS["carve"])
    truth = dataset.truth_mesh()  # before the work: a bad truth model fails at once
    given = depth is not None or tilt is not None
    tilt = None if tilt is None else math.radians(tilt)
    surface = dataset.manifest.surface
    deep = deep_water(dataset.manifest, depth, tilt)
    if not deep:
        check_depth_tilt(surface.depth if depth is None else depth, surface.tilt if tilt is None else tilt)
    box = None if box is None else check_box(np.reshape(box, (2, 3)))
    backend = state.get_backend()
    state.echo(f"carving {dataset_dir}: {len(dataset.images)} views, resolution {resolution} "
               f"({backend.name} on {backend.device})")
    result = run(dataset, depth, tilt, resolution=resolution, box=box,
                 settings=dataclasses.replace(CarveSettings(), faces=faces), backend=backend)
    voxels, mesh = result.voxels, result.mesh
    state.echo(f"  depth {result.depth:.4g} m, tilt {math.degrees(result.tilt):.4g} deg "
               f"({'known, deep water' if deep else 'given' if given else 'measured'}); {voxels.kept} voxels of "
               f"{voxels.voxel_size * 1e3:.3g} mm kept; mesh {len(mesh.faces)} triangles, "
               f"{mesh.volume * 1e6:.4g} cm3")
    record = carve_record(dataset_dir, dataset, result, resolution=resolution, given=given, load_s=loaded,
                          truth=truth)
    if deep:
        record["depth_tilt_source"] = "known"  # deep water: fsswarp.dataset.deep_water_pose
    metrics = record["metrics"]
    if metrics is not None:
        state.echo(f"  vs truth: E_V {metrics['E_V']:.3f}, true volume kept {metrics['truth_volume_kept']:.3f}, "
                   f"Chamfer {metrics['chamfer_m'] * 1e3:.2f} mm, F-score {metrics['fscore']:.3f} "
                   f"(tau {metrics['tau_m'] * 1e3:.2f} mm)")
    with output_folder(out, marker=MARKERS["carve"]) as tmp:
        write_carve(tmp, result, record)
        carve_figure(mesh, tmp / "carve.png", truth=truth,
                     title=f"{dataset_dir.name}: carved (D = {result.depth:.3f} m, tilt = "
                           f"{math.degrees(result.tilt):.2f} deg)" + (" over the truth" if truth is not None else ""))
    state.echo(f"wrote {out}: carved.ply, carve.json, carve.png ({sum(record['timings_s'].values()):.2f} s)")


@app.command()
@click.argument("dataset_dir", metavar="DIR", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for model.ply, carved.ply, result.json and figures/.")
@click.option("--iterations", default=10, show_default=True, type=click.IntRange(min=0),
              help="Most pose + shape iterations after the carving.")
@click.option("--patience", default=2, show_default=True, type=click.IntRange(min=1),
              help="Stop after this many iterations in a row without a new lowest image error E_I.")
@click.option("--resolution", default=128, show_default=True, type=click.IntRange(16, 1024),
              help="Voxels along the longest side of the carving box.")
@start_options
@click.pass_obj
def reconstruct(state: State, dataset_dir: Path, out: Path, iterations: int, patience: int, resolution: int, depth,
                tilt) -> None:
    """Reconstruct the object and estimate the sonar's depth and tilt from the dataset DIR
    (carve, then alternate pose and shape steps): OUT/model.ply, OUT/carved.ply,
    OUT/result.json and OUT/figures/."""
    from .atomic import check_output_folder
    from .dataset import load_dataset
    from .pose import check_start, check_uncertainties
    from .reconstruction import ReconstructSettings
    from .errors import check_depth_tilt

    dataset = load_dataset(dataset_dir)
    check_output_folder(out, marker=MARKERS["reconstruct"])
    if not deep_water(dataset.manifest, depth, tilt):  # deep water: no start to check, no pose step
        surface = dataset.manifest.surface
        depth0, tilt0 = surface.depth if depth is None else depth, surface.tilt if tilt is None else math.radians(tilt)
        check_depth_tilt(depth0, tilt0)
        check_start(dataset, depth0, tilt0)  # the priors' sigmas first (Prior.of)
        check_uncertainties(dataset, depth0)
        if iterations:  # only the loop and its answer mesh carvings ahead
            state.start_mesh_workers()
    run_reconstruction(state, dataset, out,
                       ReconstructSettings(iterations=iterations, patience=patience, resolution=resolution),
                       state.figure_drawer(), depth0=depth, tilt0=None if tilt is None else math.radians(tilt))


@app.command()
@click.argument("jobs_file", metavar="JOBS.toml", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for one reconstruction folder per job (OUT/<name>/), jobs.jsonl and summary.json.")
@click.option("--address", default=None,
              help="Ray cluster to join: 'auto' or HOST:PORT of its head; default: start a local Ray instance.")
@click.option("--jobs-per-gpu", default=1, show_default=True, type=click.IntRange(min=1),
              help="Jobs sharing each GPU at once (each asks Ray for 1/K of a GPU); CPU-only clusters run one "
                   "job per CPU on OpenCL.")
@click.option("--retries", default=2, show_default=True, type=click.IntRange(min=0),
              help="Runs again of a job that was killed, crashed or lost its worker (bad input is not retried).")
@click.option("--warm-up/--no-warm-up", "warm_up", default=None,
              help="Compile the kernels on every node ('fsswarp info --warm-up') before the first job; default: "
                   "unless the jobs run on OpenCL, which builds its programs as each worker's process starts.")
@click.option("--jobs-per-process", default=0, show_default=True, type=click.IntRange(min=0),
              help="Jobs that one resident process runs one after another before a fresh one starts (0: no "
                   "limit; 1: a fresh process per job).")
@click.pass_obj
def batch(state: State, jobs_file: Path, out: Path, address, jobs_per_gpu: int, retries: int, warm_up,
          jobs_per_process: int) -> None:
    """Run the reconstructions of JOBS.toml on a Ray cluster (or a local Ray instance), one
    'fsswarp reconstruct' per job: OUT/<name>/, OUT/jobs.jsonl (one line per job: ok, failed or
    skipped) and OUT/summary.json. Jobs already done are skipped. Exit 1 if any job failed."""
    from .batch import load_jobs, run_batch

    jobs = load_jobs(jobs_file, reconstruct)
    selection = [a for k, v in (("--backend", state.backend), ("--device", state.device)) if v not in (None, "auto")
                 for a in (k, v)]
    outcomes = run_batch(jobs, out, address=address, jobs_per_gpu=jobs_per_gpu, retries=retries,
                         global_options=tuple(selection), quiet=state.quiet, warm_up=warm_up,
                         jobs_per_process=jobs_per_process)
    if any(o.status == "failed" for o in outcomes):
        click.get_current_context().exit(1)


@app.command("report")
@click.argument("folder", metavar="OUT", type=click.Path(path_type=Path))
@click.option("--dataset", "dataset_dir", type=click.Path(path_type=Path), default=None,
              help="The dataset folder the reconstruction was made from; default: the one result.json names, "
                   "or OUT/../dataset of a demo.")
@click.pass_obj
def report_command(state: State, folder: Path, dataset_dir) -> None:
    """Write OUT/report.html, one page that opens offline in a browser: for a reconstruct
    output, the answer (D and tilt with their intervals, the errors), the history, every view
    beside its ghost-free data and the synthetic views of the carved and the final model, and
    a 3-D view of the models; for a batch output, one row per job, linked to each job's page
    (written too where it is missing)."""
    from .report import check_folder, report

    check_folder(folder, dataset_dir)  # before the backend starts
    page = report(folder, dataset_dir=dataset_dir, backend=state.get_backend(), command=command_line(),
                  drawer=state.figure_drawer())
    state.echo(f"wrote {page}")


def command_line() -> str:
    """The command line that runs this process, as a user would type it."""
    import shlex

    return shlex.join(["fsswarp", *sys.argv[1:]])


@app.command()
@click.argument("dataset_dir", metavar="DIR", type=click.Path(path_type=Path))
@click.option("--model", required=True, type=click.Path(path_type=Path),
              help="Mesh of the object in the dataset's reference frame (a known shape, truth/model.ply of a "
                   "simulation, or OUT/model.ply of reconstruct).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for pose.json, pose.png and contours.png.")
@start_options
@click.option("--levels", default=3, show_default=True, type=click.IntRange(1, 6),
              help="Grid levels, each 9 x 9 cells around the previous level's best, at half its spacing.")
@click.option("--depth-range", type=float, default=None,
              help="Half-width of the searched depths (m), below D0; default: 3 depth_sigma_m of the manifest.")
@click.option("--tilt-range", type=float, default=None,
              help="Half-width of the searched tilts (deg), below 45; default: 3 tilt_sigma_deg of the manifest.")
@click.pass_obj
def pose(state: State, dataset_dir: Path, model: Path, out: Path, depth, tilt, levels: int, depth_range,
         tilt_range) -> None:
    """Estimate the sonar's depth D and tilt from the dataset DIR with a given MODEL of the
    object (the pose step of reconstruct, alone): the posterior cost (E_mu scaled by its noise,
    plus the sensors' priors) on a grid over D0 ± 3 depth_sigma_m and tilt0 ± 3 tilt_sigma_deg
    of the manifest (or --depth-range, --tilt-range), refined per level, then a BOBYQA polish;
    the estimate is kept only where the cost falls, with its 95% intervals. OUT/pose.json,
    OUT/pose.png (the grid levels) and OUT/contours.png (per view, the data's contours and
    the model's at the estimate and at the start)."""
    from .atomic import check_output_folder, output_folder
    from .compare import PoseWarning, view_contours
    from .dataset import load_dataset
    from .figures import contours_figure, pose_figure
    from .outputs import pose_record, write_pose
    from .pose import check_start, check_uncertainties, estimate_pose
    from .errors import check_depth_tilt

    dataset = load_dataset(dataset_dir)
    mesh = load_mesh_file(model, "--model")
    check_output_folder(out, marker=MARKERS["pose"])
    if deep_water(dataset.manifest):
        raise InputError("has no sea surface (deep water, no [surface] table): its depth and tilt are known, there is "
                         "nothing to estimate", file=dataset_dir / "dataset.toml", field="surface")
    surface = dataset.manifest.surface
    depth0, tilt0 = surface.depth if depth is None else depth, surface.tilt if tilt is None else math.radians(tilt)
    check_depth_tilt(depth0, tilt0)
    check_start(dataset, depth0, tilt0)  # the priors' sigmas first (Prior.of)
    bounds = check_uncertainties(dataset, depth0, depth_range=depth_range,
                                 tilt_range=None if tilt_range is None else math.radians(tilt_range))
    backend = state.get_backend()
    drawer = state.figure_drawer()
    given = depth is not None or tilt is not None
    state.echo(f"estimating depth and tilt of {dataset_dir} with {model}: {levels} grid levels "
               f"({backend.name} on {backend.device})")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoseWarning)  # the views left out are listed below
            result = estimate_pose(mesh, dataset, depth0=depth0, tilt0=tilt0, bounds=bounds, levels=levels,
                                   backend=backend, progress=lambda line: state.echo("  " + line))
            contours = view_contours(mesh, dataset, result.depth, result.tilt, at=[(result.depth0, result.tilt0)],
                                     backend=backend)
    except InputError as err:
        if err.field != "model":
            raise
        raise InputError(err.message, field="--model", value=str(model)) from None
    edges = result.box_edges()
    if edges:
        warnings.warn(f"the grid search ended on the {' and '.join(edges)} edge of its box (D0 +- "
                      f"{bounds[0]:.4g} m, tilt0 +- {math.degrees(bounds[1]):.4g} deg): the truth may lie beyond it; "
                      "start nearer (--depth/--tilt) or search wider (--depth-range/--tilt-range)", PoseWarning,
                      stacklevel=2)
    record = pose_record(dataset_dir, model, dataset, result, contours, given=given, backend=backend)
    left_out = record["views_left_out"]
    truth = dataset.manifest.truth
    if truth is not None:
        state.echo(f"  vs truth: D {1e3 * (result.depth - truth.depth):+.1f} mm, tilt "
                   f"{math.degrees(result.tilt - truth.tilt):+.3f} deg (from {1e3 * (result.depth0 - truth.depth):+.1f}"
                   f" mm, {math.degrees(result.tilt0 - truth.tilt):+.3f} deg)")
    if left_out:
        state.echo(f"  views left out (the model is not seen in them): {', '.join(left_out)}")
    with output_folder(out, marker=MARKERS["pose"]) as tmp, drawer.batch() as draw:
        draw(pose_figure, result, tmp / "pose.png", truth=None if truth is None else (truth.depth, truth.tilt),
             title=f"{dataset_dir.name}: the (D, tilt) grid search with {model.name}")
        draw(contours_figure, dataset.images, contours, dataset.sonar, tmp / "contours.png",
             title=f"{dataset_dir.name}: frontal contours of the data and of {model.name} at the estimate "
                   f"(D {result.depth:.4f} m, tilt {math.degrees(result.tilt):.3f} deg) and at the start "
                   f"(D {result.depth0:.4f} m, tilt {math.degrees(result.tilt0):.3f} deg)")
        write_pose(tmp, record)
    (d0, d1), (t0, t1) = result.posterior.interval(0), result.posterior.interval(1)
    state.echo(f"wrote {out}: depth {result.depth:.4f} m (95%: {d0:.4f}-{d1:.4f} m), tilt "
               f"{math.degrees(result.tilt):.2f} deg (95%: {math.degrees(t0):.2f}-{math.degrees(t1):.2f} deg) "
               f"({'moved' if result.accepted else 'kept: the posterior cost did not fall'}), pose.json, pose.png, "
               f"contours.png ({result.seconds:.1f} s)")


@app.command()
@click.argument("scene_name", metavar="[SCENE]", default="coral-one")
@click.option("--out", default=Path("demo-out"), show_default=True, type=click.Path(path_type=Path),
              help="Folder for the dataset (OUT/dataset), the reconstruction (OUT/reconstruction) and the "
                   "ghost-free views (OUT/enhance).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Noise seed.")
@click.option("--iterations", default=10, show_default=True, type=click.IntRange(min=0),
              help="Most pose + shape iterations after the carving.")
@click.pass_obj
def demo(state: State, scene_name: str, out: Path, seed: int, iterations: int) -> None:
    """Simulate a built-in scene (coral-one, coral-two, table) or a scene file, reconstruct it
    from its noisy images and measured depth and tilt, and remove the ghosts from its views
    with the reconstruction: OUT/dataset, OUT/reconstruction, OUT/enhance, with figures."""
    import time

    from .atomic import check_output_folder, output_folder
    from .reconstruction import ReconstructSettings
    from .simulation import check_scene
    from .simulation import simulate as run_simulation

    check_output_folder(out, marker=MARKERS["demo"])
    if check_scene(scene_name)[0].deep_water:
        raise InputError("is a deep-water scene (no [surface]): it has no ghosts to remove; run simulate and reconstruct",
                         field="SCENE", value=scene_name)
    if iterations:  # only the loop and its answer mesh carvings ahead
        state.start_mesh_workers()
    backend = state.get_backend()
    start = time.perf_counter()
    with output_folder(out, marker=MARKERS["demo"]) as tmp:
        drawer = state.figure_drawer()
        state.echo(f"simulating {scene_name} ({backend.name} on {backend.device})")
        dataset = run_simulation(scene_name, tmp / "dataset", seed=seed, backend=backend)
        # every figure is drawn while the later steps run; the folders are finished at the end
        with ExitStack() as later:
            simulation_figure(dataset, tmp / "dataset" / "figures" / "layers.png", later.enter_context(drawer.batch()))
            state.echo(f"  {len(dataset.images)} noisy views in {time.perf_counter() - start:.1f} s")
            settings = ReconstructSettings(iterations=iterations)

            def enhancement(result) -> dict:  # before the report's views, so its figures are drawn first
                return run_enhancement(state, dataset, result.model, "the reconstructed model", result.depth,
                                       result.tilt, tmp / "enhance", drawer, source="estimated",
                                       initial=(result.carved, "the carved model"), shown=out / "enhance",
                                       dataset_label=out / "dataset", name=Path(scene_name).stem, later=later)

            run_reconstruction(state, dataset, tmp / "reconstruction", settings, drawer, shown=out / "reconstruction",
                               name=Path(scene_name).stem, later=later, before_report=enhancement)
            state.echo("finishing the figures and the report")
        (tmp / "demo.json").write_text(json.dumps({"scene": scene_name, "seed": seed,
                                                   "seconds": time.perf_counter() - start}, indent=2))
    state.echo(f"wrote {out}: dataset/, reconstruction/, enhance/ ({time.perf_counter() - start:.1f} s in all)")
    state.echo(f"report: {out / 'reconstruction' / 'report.html'}")


def run_reconstruction(state: State, dataset, out: Path, settings, drawer, *, depth0: float | None = None,
                       tilt0: float | None = None, shown: Path | None = None, name: str | None = None,
                       later: ExitStack | None = None, before_report: Callable | None = None):
    """Reconstruct ``dataset`` from (depth0 m, tilt0 rad; default the measured values), write
    OUT/model.ply, carved.ply, result.json and figures (drawn by ``drawer``, a
    ``fsswarp.figures.FigureDrawer``; ``shown``: the folder's name in messages, when OUT is a
    temporary folder; ``name``: the scene's in titles, default the dataset folder's) and
    OUT/report.html (``fsswarp.report``); returns the ReconstructResult. ``later``: an ExitStack
    whose closing finishes OUT (its figures, the report, the rename; default: before returning).
    ``before_report``: called with the result once the summary is said and the figures are
    queued, before the report's views (the demo's enhancement: its figures, the slowest, are then
    drawn before the report's); what it returns, the views enhanced with the final model at the
    estimate ({view: EnhancedView}), the report's rows show (``write_report``'s ``enhanced``)."""
    from .atomic import output_folder
    from .compare import PoseWarning, view_contours
    from .figures import carve_figure, contours_figure, history_figure, pose_figure
    from .outputs import write_reconstruction
    from .report import write_report
    from .reconstruction import reconstruct as run

    backend = state.get_backend()
    state.echo(f"reconstructing {len(dataset.images)} views ({backend.name} on {backend.device})")
    result = run(dataset, depth0=depth0, tilt0=tilt0, settings=settings, backend=backend,
                 progress=lambda line: state.echo("  " + line))
    truth = dataset.manifest.truth
    truth_mesh = dataset.truth_mesh()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)  # the figure shows the views where the model is seen
        contours = view_contours(result.model, dataset, result.depth, result.tilt, settings=settings.pose,
                                 backend=backend)
    with ExitStack() as own:
        finish = own if later is None else later
        tmp = finish.enter_context(output_folder(out, marker=MARKERS["reconstruct"]))
        draw = finish.enter_context(drawer.batch())
        write_reconstruction(tmp, result)
        draw(carve_figure, result.carved, tmp / "figures" / "carved.png", truth=truth_mesh,
             title=f"{name or dataset.root.name}: carved model (iteration 0)")
        draw(carve_figure, result.model, tmp / "figures" / "model.png", truth=truth_mesh, label="final",
             title=f"{name or dataset.root.name}: final model (iteration {result.best_iteration}, the lowest E_I)")
        draw(contours_figure, dataset.images, contours, dataset.sonar, tmp / "figures" / "contours.png",
             labels=("final",),
             title=f"{name or dataset.root.name}: frontal contours of the data and of the final model (iteration "
                   f"{result.best_iteration}) at D {result.depth:.3f} m, tilt {math.degrees(result.tilt):.2f} deg")
        draw(history_figure, result.history, tmp / "figures" / "history.png",
             truth_depth=None if truth is None or truth.depth is None else truth.depth,
             truth_tilt_deg=None if truth is None or truth.depth is None else math.degrees(truth.tilt),
             best_iteration=result.best_iteration,
             title=f"{name or dataset.root.name}: depth and tilt, and errors, per iteration")
        if result.pose_steps:
            draw(pose_figure, result.pose_steps[0], tmp / "figures" / "pose.png",
                 truth=None if truth is None else (truth.depth, truth.tilt),
                 title="first pose step: the (D, tilt) grid search around the measured values")
        enhanced = None
        if before_report is not None:
            _say_reconstructed(state, dataset, result, shown or out)
            enhanced = before_report(result)
        write_report(tmp, dataset=dataset, backend=backend, command=command_line(), name=name, drawer=drawer,
                     later=finish, enhanced=enhanced)
    if before_report is None:
        _say_reconstructed(state, dataset, result, shown or out)
    return result


def _say_reconstructed(state: State, dataset, result, shown: Path) -> None:
    """The summary of a reconstruction written to the folder ``shown``: the estimate and its
    intervals, the start and the error against a truth, a warning for what is not identified."""
    from .compare import PoseWarning
    from .pose import Z95
    from .report import REPORT_FILE

    best = result.history[result.best_iteration]
    if dataset.manifest.deep_water:  # no pose step: the known depth and tilt, no intervals
        state.echo(f"wrote {shown}: E_I {best['E_I']:.3f} (iteration {result.best_iteration} of "
                   f"{result.iterations}, {'stopping rule met' if result.stopped else 'iteration limit'}), "
                   f"{result.seconds:.1f} s; no pose step: the dataset has no sea surface (deep water)")
        return
    summary = result.summary()
    (d0, d1), (t0, t1) = summary["depth_interval_m"], summary["tilt_interval_deg"]
    stop = "stopping rule met" if result.stopped else "iteration limit"
    state.echo(f"wrote {shown}: depth {result.depth:.4f} m (95%: {d0:.4f}-{d1:.4f} m), tilt "
               f"{math.degrees(result.tilt):.2f} deg (95%: {t0:.2f}-{t1:.2f} deg), E_I {best['E_I']:.3f} "
               f"(iteration {result.best_iteration} of {result.iterations}, {stop}; "
               f"{'converged' if result.converged else 'not converged'}), {result.seconds:.1f} s")
    start = summary["start"]
    state.echo(f"  started from depth {start['depth_m']:.4f} m, tilt {start['tilt_deg']:.2f} deg" + (
        "" if summary["error_vs_truth"] is None else
        f"; error against the truth: depth {summary['error_vs_truth']['depth_m'] * 1e3:+.1f} mm, tilt "
        f"{summary['error_vs_truth']['tilt_deg']:+.2f} deg"))
    unidentified = [name for name, known in summary["identified"].items() if not known]
    if unidentified:
        prior = result.posterior.prior
        widths = {"depth": f"{(d1 - d0) * 1e3:.1f} mm against the sensor's {2 * Z95 * prior.depth_sigma * 1e3:.1f} mm",
                  "tilt": f"{t1 - t0:.2f} deg against the sensor's {2 * Z95 * math.degrees(prior.tilt_sigma):.2f} deg"}
        _show_warning(f"not identified by the images: {' and '.join(unidentified)} (95% interval "
                      f"{'; '.join(widths[name] for name in unidentified)}: not half as wide), so the run is not "
                      f"called converged; the estimate of {' and '.join(unidentified)} rests on the sensor",
                      PoseWarning, __file__, 0)
    state.echo(f"report: {shown / REPORT_FILE}")


@app.command()
@click.argument("dataset_dir", metavar="DIR", type=click.Path(path_type=Path))
@click.option("--model", required=True, type=click.Path(path_type=Path),
              help="Mesh of the object in the dataset's reference frame (e.g. OUT/model.ply of reconstruct).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Folder for <view>_enhanced.tiff, <view>_ghost.tiff, enhance.json and the figures.")
@click.option("--depth", type=float, default=None, help="Sonar depth D (m); default: the dataset's measured depth.")
@click.option("--tilt", type=float, default=None, help="Sonar tilt (deg); default: the dataset's measured tilt.")
@click.option("--view", "view_names", multiple=True, help="Enhance only this view (repeatable).")
@click.option("--initial-model", type=click.Path(path_type=Path), default=None,
              help="Initial mesh (e.g. OUT/carved.ply of reconstruct), rendered at the measured depth and tilt "
                   "as the comparison figures' 'initial synthetic' column.")
@click.option("--ghost-sigma", nargs=2, type=float, default=(0.0, 0.0), show_default=True,
              metavar="BINS BEAMS", help="Despeckle the isolated ghost (Gaussian sigma inside the ghost region, "
                                         "0 to 20 pixels); 0 0 keeps the recorded ghost, 1 0.7 estimates the "
                                         "noise-free one.")
@click.pass_obj
def enhance(state: State, dataset_dir: Path, model: Path, out: Path, depth, tilt, view_names, initial_model,
            ghost_sigma) -> None:
    """Remove the ghost from every view by the LUT method of the paper's §2.6 and isolate the
    ghost: OUT/<view>_enhanced.tiff and OUT/<view>_ghost.tiff (the data's linear units),
    OUT/enhance.json (regions, LUTs and, for simulated data, scores against the truth layers),
    OUT/enhance.png, and the figures of the paper's Figures 10-14, OUT/views_optimized.png and
    OUT/views_heldout.png (data | ghost-free | [initial synthetic |] synthetic of MODEL). Views
    that MODEL does not project into are skipped with a warning; none at all is an error."""
    from .atomic import check_output_folder
    from .dataset import load_dataset
    from .enhancement import check_ghost_sigma, check_views
    from .errors import check_depth_tilt

    dataset = load_dataset(dataset_dir)
    mesh = load_mesh_file(model, "--model")
    check_output_folder(out, marker=MARKERS["enhance"])
    check_ghost_sigma(tuple(ghost_sigma))
    if deep_water(dataset.manifest):
        raise InputError("has no sea surface (deep water, no [surface] table): its views hold no ghost to remove",
                         file=dataset_dir / "dataset.toml", field="surface")
    initial = None
    if initial_model is not None:
        initial = (load_mesh_file(initial_model, "--initial-model"), str(initial_model))
    given = depth is not None or tilt is not None
    depth = dataset.manifest.surface.depth if depth is None else depth
    tilt = dataset.manifest.surface.tilt if tilt is None else math.radians(tilt)
    check_depth_tilt(depth, tilt)
    check_views(dataset, list(view_names))
    run_enhancement(state, dataset, mesh, str(model), depth, tilt, out, state.figure_drawer(),
                    views=list(view_names) or None, source="given" if given else "measured", initial=initial,
                    ghost_sigma=tuple(ghost_sigma))


def run_enhancement(state: State, dataset, mesh, model_name: str, depth: float, tilt: float, out: Path, drawer, *,
                    views=None, source: str, initial=None, ghost_sigma=(0.0, 0.0), shown: Path | None = None,
                    dataset_label: Path | None = None, name: str | None = None, later: ExitStack | None = None) -> dict:
    """Enhance ``dataset``'s views with ``mesh`` at (depth m, tilt rad) and write OUT/<view>_enhanced.tiff,
    <view>_ghost.tiff, enhance.json, enhance.png and the comparison figures (COMPARISON_FIGURES; a
    group with no view gets none; ``fsswarp.outputs``), the figures drawn by ``drawer`` (a
    ``fsswarp.figures.FigureDrawer``). ``initial``: (mesh, name) of the initial model, rendered at the
    measured depth and tilt for the figures' "initial synthetic" column; ``ghost_sigma``: see
    fsswarp.enhancement.enhance_view. ``shown``, ``dataset_label``:
    the names of OUT and of the dataset's folder in messages and enhance.json, when they are
    temporary folders; ``name``: the scene's in titles (default the dataset folder's); ``later``:
    an ExitStack whose closing finishes OUT (its figures, the rename; default: before returning).
    Returns the enhanced views, {view: fsswarp.enhancement.EnhancedView}."""
    import time

    import numpy as np

    from .atomic import output_folder
    from .enhancement import comparison_views, match_level, render_model
    from .enhancement import enhance as run
    from .figures import comparison_figure, enhance_figure
    from .outputs import (COMPARISON_FIGURES, comparison_figures, enhancement_record, enhancement_scores,
                          write_enhancement)
    from .rendering import LAYERS

    start = time.perf_counter()
    backend = state.get_backend()
    requested = list(views or dataset.rig.names)
    state.echo(f"enhancing {len(requested)} views with {model_name}: D {depth:.4g} m, "
               f"tilt {math.degrees(tilt):.4g} deg ({source}; {backend.name} on {backend.device})")
    results = run(dataset, mesh, depth, tilt, views=requested, backend=backend, model_name=model_name,
                  ghost_sigma=ghost_sigma)
    groups = comparison_views(dataset.rig, list(results))
    surface = dataset.manifest.surface
    initial_layers = None
    if initial is not None:
        initial_layers = render_model(initial[0], dataset, surface.depth, surface.tilt,
                                      groups["optimized"] + groups["held-out"], backend=backend, model_name=initial[1])
    scores = enhancement_scores(dataset, results)
    if scores is not None:
        reductions = [s["mae_reduction"] for s in scores.values() if s["mae_reduction"] is not None]
        correlations = [s["ghost_corr"] for s in scores.values() if s["ghost_corr"] is not None]
        if reductions:
            state.echo(f"  vs truth: MAE in the overlap {100 * np.mean(reductions):.1f}% lower than the raw data's "
                       f"(mean; min {100 * min(reductions):.1f}%) over {len(reductions)} views")
        if correlations:
            state.echo(f"  isolated ghost vs true ghost: Pearson r {np.mean(correlations):.3f} "
                       f"(mean; min {min(correlations):.3f})")
    figures = comparison_figures(groups, initial=initial is not None)
    label = name or (dataset_label or dataset.root).name
    record = enhancement_record(dataset, results, model_name=model_name, depth=depth, tilt=tilt, source=source,
                                requested=requested, initial_name=None if initial is None else initial[1],
                                ghost_sigma=ghost_sigma, scores=scores, figures=figures, backend=backend,
                                seconds=time.perf_counter() - start, dataset_label=dataset_label)
    with ExitStack() as own:
        finish = own if later is None else later
        tmp = finish.enter_context(output_folder(out, marker=MARKERS["enhance"]))
        draw = finish.enter_context(drawer.batch())
        write_enhancement(tmp, results, record)
        first = list(results)[:6]
        draw(enhance_figure, {n: dataset.images[n] for n in first}, {n: results[n] for n in first}, dataset.sonar,
             tmp / "enhance.png", title=f"{label}: ghost removal with {model_name}"
             + (f" (first 6 of {len(results)} views)" if len(results) > 6 else ""))
        total = LAYERS.index("total")
        for file, entry in figures.items():
            names = entry["views"]
            initial_images = None if initial is None else {
                n: match_level(initial_layers[n][total], dataset.images[n]) if n in initial_layers
                else np.zeros_like(dataset.images[n]) for n in names}
            group = "held-out views (not optimized)" if COMPARISON_FIGURES[file] == "held-out" else "optimized views"
            draw(comparison_figure, {n: dataset.images[n] for n in names},
                 {n: results[n].enhanced for n in names},
                 {n: match_level(results[n].synthetic, dataset.images[n]) for n in names},
                 dataset.sonar, tmp / file, initial=initial_images,
                 title=f"{label}, {group}: {', '.join(names)}\n"
                       + (f"initial synthetic: {initial[1]} at the measured D0 = {surface.depth:.3f} m, "
                          f"tilt {math.degrees(surface.tilt):.2f} deg\n" if initial is not None else "")
                       + f"optimized synthetic: {model_name} at D = {depth:.3f} m, tilt "
                         f"{math.degrees(tilt):.2f} deg ({source})\nsynthetic: total layer, scaled to "
                         "the data's mean over its returns")
    state.echo(f"wrote {shown or out}: {len(results)} views, enhance.json, enhance.png"
               + "".join(f", {file}" for file in figures) + f" ({time.perf_counter() - start:.1f} s)")
    return results


def describe_manifest(manifest) -> str:
    """A few lines that summarize a manifest for people."""
    sonar, surface, rig = manifest.sonar, manifest.surface, manifest.rig
    lines = [
        f"  sonar: {sonar.beams} beams x {sonar.bins} bins, azimuth {math.degrees(sonar.azimuth_fov):.4g} deg, "
        f"elevation {math.degrees(sonar.elevation_fov):.4g} deg, range {sonar.range_min:g}-{sonar.range_max:g} m"
        + (", beam angle table" if sonar.beam_angles is not None else ""),
        f"  surface (measured): depth {surface.depth:.4g} m +/- {surface.depth_sigma:.3g}, "
        f"tilt {math.degrees(surface.tilt):.4g} deg +/- {math.degrees(surface.tilt_sigma):.3g}" if surface is not None
        else f"  surface: none in view (deep water); depth {manifest.known_pose.depth:.4g} m, tilt "
             f"{math.degrees(manifest.known_pose.tilt):.4g} deg known ([rig])",
    ]
    if manifest.truth is not None and manifest.truth.depth is not None:
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


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fsswarp: warning: {' '.join(str(message).split())}", file=sys.stderr)


def run() -> None:
    """The ``fsswarp`` command (console script and ``python -m fsswarp``): :func:`main`, then the
    process's end. Its other threads are joined and its exit handlers run (child processes
    stopped), and then it ends at once, without the interpreter's teardown: a GPU demo's process
    ended 0.36–0.42 s after its last line, 0.16–0.19 s so (docs/decisions.md). With a profiler or
    tracer attached, which writes its results at the teardown, it ends as usual."""
    import atexit
    import threading

    from .processes import exit_now

    status = main()
    if sys.gettrace() is not None or sys.getprofile() is not None:
        sys.exit(status)
    threading._shutdown()  # the interpreter's own first steps at its end: idle pools told to stop, threads joined
    atexit._run_exitfuncs()
    exit_now(status)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            status = app.main(args=argv, prog_name="fsswarp", standalone_mode=False)
    except InputError as err:
        print(f"fsswarp: error: {err}", file=sys.stderr)
        return 2
    except click.exceptions.NoArgsIsHelpError as err:
        click.echo(err.ctx.get_help())
        return 2
    except click.UsageError as err:
        named = [a for a in (sys.argv[1:] if argv is None else argv) if a in app.commands]
        command = err.ctx.command_path if err.ctx is not None else " ".join(["fsswarp"] + named[:1])
        message = " ".join(err.format_message().split())
        print(f"fsswarp: error: {message} (see '{command} --help')", file=sys.stderr)
        return 2
    except click.exceptions.Exit as done:
        return done.exit_code
    except OSError as err:  # a path that cannot be read or searched (too long, no permission): one line
        if err.filename is None:
            raise
        print(f"fsswarp: error: {err.filename}: {err.strerror}", file=sys.stderr)
        return 2
    except (click.Abort, KeyboardInterrupt):
        print("fsswarp: interrupted", file=sys.stderr)
        return 130
    return status if isinstance(status, int) else 0  # ctx.exit(n)'s status (click returns it)
