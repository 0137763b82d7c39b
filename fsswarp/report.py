"""``fsswarp report``: a reconstruction, or a batch of them, as one HTML page (docs/report.md).

:func:`write_report` writes OUT/report.html for the output folder of ``fsswarp reconstruct``:
the answer (D and β with their intervals beside the sensors' values and the truth, E_I and,
with a truth model, E_V, Chamfer and F-score), the history plots, per view the data, the
ghost-free data and the synthetic views of the carved and of the final model as fan images
(paper Figures 10–14), a WebGL view of the carved model, the final model and the truth, and
how it was made. :func:`write_batch_report` writes DIR/report.html for ``fsswarp batch``: one
row per job, linked to the job's page. :func:`report` picks one by what the folder holds.

The page is one file that asks nothing of the network: images are PNG data URIs, the script
and the style sheet (``fsswarp/data/report/``) are inline, and its Content-Security-Policy
refuses any request. Every number shown is an element ``<data class="num">`` with
``data-source`` (the file it comes from: result.json, dataset.toml, or "computed" from two of
them), ``data-key`` (its path there, e.g. ``history[3].E_V``), ``data-scale`` and
``data-format`` (a Python format spec): the text shown is ``format(value × scale, format)``.
"""

from __future__ import annotations

import base64
import datetime
import html
import json
import math
import platform
import tempfile
import time
import warnings
from contextlib import ExitStack, nullcontext
from importlib import metadata, resources
from pathlib import Path

import numpy as np

from .atomic import on_success, write_text
from .batch import DONE_MARKER, JOBS_FILE
from .errors import InputError, is_finite_number

#: The page's file name, in the reconstruction or batch folder.
REPORT_FILE = "report.html"
#: The file of ``fsswarp reconstruct`` that the report reads.
RESULT_FILE = "result.json"
#: The keys of result.json the report needs.
REQUIRED_KEYS = ("depth_m", "tilt_deg", "best_iteration", "iterations", "converged", "backend", "device", "seconds",
                 "history")
#: The packages whose versions "how it was made" lists.
PACKAGES = ("fsswarp", "numpy", "scipy", "warp-lang", "pyopencl", "trimesh", "matplotlib")


def report(folder, *, dataset_dir=None, backend=None, command: str = "", drawer=None) -> Path:
    """Write the report of ``folder``: :func:`write_report` for a reconstruction folder (with
    result.json, or a demo's folder), :func:`write_batch_report` for a batch folder (with
    jobs.jsonl); returns the page's path. InputError (:func:`check_folder`) before anything is
    written."""
    folder = check_folder(folder, dataset_dir)
    if (folder / RESULT_FILE).is_file():
        return write_report(folder, dataset_dir=dataset_dir, backend=backend, command=command, drawer=drawer)
    return write_batch_report(folder, backend=backend, command=command, drawer=drawer)


def check_folder(folder, dataset_dir=None) -> Path:
    """The folder :func:`report` writes into: ``folder`` if it is a reconstruction (whose
    result.json is read and whose dataset is found) or a batch folder, a demo's reconstruction
    folder; InputError for any other folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such folder" if not folder.exists() else "is not a folder", field="OUT",
                         value=str(folder))
    if (folder / "demo.json").is_file() and (folder / "reconstruction" / RESULT_FILE).is_file():
        folder = folder / "reconstruction"  # a demo's folder: its reconstruction
    if (folder / RESULT_FILE).is_file():
        _find_dataset(folder, read_result(folder / RESULT_FILE), dataset_dir)
        return folder
    if dataset_dir is not None:
        raise InputError("applies to a reconstruction folder only (with result.json)", field="--dataset",
                         value=str(dataset_dir))
    if (folder / JOBS_FILE).is_file():
        _read_jobs(folder / JOBS_FILE)
        return folder
    raise InputError(f"is neither a reconstruction output (no {RESULT_FILE}) nor a batch output (no {JOBS_FILE})",
                     field="OUT", value=str(folder))


# --- one reconstruction ----------------------------------------------------------------------

def write_report(folder, *, dataset=None, dataset_dir=None, backend=None, command: str = "", name: str | None = None,
                 drawer=None, later: ExitStack | None = None, enhanced: dict | None = None) -> Path:
    """Write FOLDER/report.html for the reconstruction in FOLDER (result.json, model.ply,
    carved.ply) of ``dataset`` (a loaded Dataset), or of the dataset folder ``dataset_dir``,
    else the one result.json names, else FOLDER/../dataset of a demo. ``backend`` renders the
    views (default: auto); ``command``: the command line shown; ``name``: the scene's name in
    titles (default: the demo's scene, else the dataset folder's name); ``drawer``: a
    ``fsswarp.figures.FigureDrawer`` for the figures (None: drawn here). ``later``: an ExitStack
    whose closing writes the page once its figures are drawn (default: before returning), so
    that the caller goes on while they are. ``enhanced``: the caller's enhancement
    (``fsswarp.enhancement.enhance``) of the views with FOLDER's final model at its estimate,
    {view: EnhancedView}, which the views' rows then show instead of enhancing them again (the
    demo's); a view it lacks is shown as not enhanced. Returns the page's path."""
    from .backends import get_backend
    from .dataset import read_mesh

    started = time.perf_counter()
    folder = Path(folder)
    result = read_result(folder / RESULT_FILE)
    dataset = dataset if dataset is not None else _find_dataset(folder, result, dataset_dir)
    meshes = {"carved": read_mesh(folder / "carved.ply", field="carved.ply"),
              "final": read_mesh(folder / "model.ply", field="model.ply")}
    truth_mesh = dataset.truth_mesh()
    if truth_mesh is not None:
        meshes["truth"] = truth_mesh
    backend = backend or get_backend()
    name = name or _scene_name(folder, dataset)
    stages = {"read the reconstruction and the dataset": time.perf_counter() - started}
    begin = time.perf_counter()
    rows, skipped = _view_rows(dataset, result, meshes, backend, enhanced)
    stages["render the views and remove the ghosts"] = time.perf_counter() - begin
    begin = time.perf_counter()

    def write_page(figures: dict[str, bytes]) -> None:
        stages["draw the figures"] = time.perf_counter() - begin
        write_text(folder / REPORT_FILE, _page(folder, result, dataset, meshes, figures, skipped, name=name,
                                               command=command, backend=backend, stages=stages))

    with ExitStack() as own:
        _draw_figures(result, dataset, rows, name, drawer, own if later is None else later, write_page)
    return folder / REPORT_FILE


def read_result(path: Path) -> dict:
    """result.json at ``path``, checked for the keys the report reads (InputError naming the
    file and the key otherwise)."""
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"not a valid JSON file: {err}", file=path) from None
    if not isinstance(result, dict):
        raise InputError("must hold a JSON object", file=path)
    for key in REQUIRED_KEYS:
        if key not in result:
            raise InputError("missing: is this a result.json of fsswarp reconstruct?", file=path, field=key)
    history = result["history"]
    if not isinstance(history, list) or not history or not all(isinstance(h, dict) for h in history):
        raise InputError("must be a list of iterations", file=path, field="history")
    best = result["best_iteration"]
    if not (isinstance(best, int) and 0 <= best < len(history)):
        raise InputError(f"must be an iteration of history (0 to {len(history) - 1})", file=path,
                         field="best_iteration", value=best)
    for key in ("depth_m", "tilt_deg"):
        if not is_finite_number(result[key]):
            raise InputError("must be a number", file=path, field=key, value=result[key])
    return result


def _find_dataset(folder: Path, result: dict, dataset_dir):
    """The reconstruction's dataset: ``dataset_dir``, else result.json's ``dataset`` (as
    written, or relative to ``folder``), else a demo's ``folder``/../dataset."""
    from .dataset import load_dataset

    if dataset_dir is not None:
        return load_dataset(dataset_dir)
    recorded = result.get("dataset")
    if isinstance(recorded, str) and recorded:
        for candidate in (Path(recorded), folder / recorded):
            if (candidate / "dataset.toml").is_file():
                return load_dataset(candidate)
    if (folder.parent / "demo.json").is_file() and (folder.parent / "dataset" / "dataset.toml").is_file():
        return load_dataset(folder.parent / "dataset")
    raise InputError("does not name the dataset folder it was made from; pass --dataset DIR",
                     file=folder / RESULT_FILE, field="dataset")


def _scene_name(folder: Path, dataset) -> str:
    """The demo's scene (demo.json beside ``folder`` or the dataset), else the dataset folder's name."""
    for place in (folder.parent, dataset.root.parent if dataset.root is not None else None):
        try:
            scene = json.loads((place / "demo.json").read_text(encoding="utf-8")).get("scene")
        except (OSError, TypeError, ValueError, AttributeError):
            continue
        if isinstance(scene, str) and scene:
            return Path(scene).stem
    return dataset.root.name if dataset.root is not None else folder.name


def _view_rows(dataset, result: dict, meshes: dict, backend, enhanced: dict | None = None) -> tuple[dict, dict]:
    """Per view, the figure's columns: {view: {column: (bins, beams) linear image}}, in rig
    order, and {view: why it is left out} for the views the final model does not reach.
    ``enhanced``: the views enhanced with the final model at the estimate already
    (:func:`write_report`), else enhanced here."""
    from .enhancement import enhance, match_level, render_model
    from .rendering import LAYERS, RenderWarning

    start = result["history"][0]
    depth0, tilt0 = float(start["depth_m"]), math.radians(float(start["tilt_deg"]))
    depth, tilt = float(result["depth_m"]), math.radians(float(result["tilt_deg"]))
    if dataset.manifest.surface is None:  # deep water: rendered where its views were synthesized
        from .dataset import deep_water_pose

        depth0, tilt0 = depth, tilt = deep_water_pose(dataset.manifest)
    names = list(dataset.rig.names)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RenderWarning)
        if enhanced is None:
            enhanced = enhance(dataset, meshes["final"], depth, tilt, views=names, backend=backend,
                               model_name="the final model")
        carved = render_model(meshes["carved"], dataset, depth0, tilt0, list(enhanced), backend=backend,
                              model_name="the carved model")
    total = LAYERS.index("total")
    rows = {}
    for view in names:
        if view not in enhanced:
            continue
        image = dataset.images[view]
        carved_image = match_level(carved[view][total], image) if view in carved else np.zeros_like(image)
        rows[view] = {"data": image, "ghost-free data": enhanced[view].enhanced,
                      f"carved model at D0 {depth0:.3f} m, β0 {math.degrees(tilt0):.2f}°": carved_image,
                      f"final model at D {depth:.3f} m, β {math.degrees(tilt):.2f}°":
                          match_level(enhanced[view].synthetic, image)}
    reasons = [" ".join(str(w.message).split()) for w in caught if issubclass(w.category, RenderWarning)]
    skipped = {view: "; ".join(r for r in reasons if view in r) or "not enhanced" for view in names
               if view not in rows}
    return rows, skipped


def _draw_figures(result: dict, dataset, rows: dict, name: str, drawer, later: ExitStack, then) -> None:
    """Draw the history figure and each view's row (``drawer``; None: here) into a temporary
    folder; when ``later`` closes, call ``then`` with their PNG bytes: {"history": ..., view: ...}."""
    from .figures import draw_here, history_figure, views_figure

    truth = dataset.manifest.truth
    tmp = Path(later.enter_context(tempfile.TemporaryDirectory(prefix="fsswarp-report-")))
    on_success(later, lambda: then({"history": (tmp / "history.png").read_bytes()}
                                   | {view: (tmp / f"view{k}.png").read_bytes() for k, view in enumerate(rows)}))
    draw = later.enter_context(drawer.batch() if drawer is not None else nullcontext(draw_here))
    draw(history_figure, result["history"], tmp / "history.png",
         truth_depth=None if truth is None else truth.depth,
         truth_tilt_deg=None if truth is None or truth.tilt is None else math.degrees(truth.tilt),
         best_iteration=result["best_iteration"], depth_interval_m=_interval(result, "depth_interval_m"),
         tilt_interval_deg=_interval(result, "tilt_interval_deg"),
         title=f"{name}: depth, tilt and errors per iteration")
    for k, (view, columns) in enumerate(rows.items()):
        draw(views_figure, {view: columns}, dataset.sonar, tmp / f"view{k}.png")


def _interval(record: dict, key: str):
    """``record[key]`` as [low, high] when it is a pair of numbers, else None."""
    value = record.get(key)
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(is_finite_number(v) for v in value):
        return [float(value[0]), float(value[1])]
    return None


def _get(record, key: str):
    """The value at ``key`` (e.g. "history[3].E_V", "valley.slope_m_per_deg") of ``record``, or
    None where it is absent."""
    value = record
    for part in key.replace("[", ".[").split("."):
        if part.startswith("["):
            index = int(part[1:-1])
            value = value[index] if isinstance(value, list) and -len(value) <= index < len(value) else None
        else:
            value = value.get(part) if isinstance(value, dict) else None
        if value is None:
            return None
    return value


def _num(value, source: str, key: str, spec: str, *, scale: float = 1.0, unit: str = "") -> str:
    """A number shown: ``<data class="num">`` with its source, key, scale and format (module
    docstring), then ``unit``; a dash where ``value`` is absent or not finite."""
    if isinstance(value, bool) or not is_finite_number(value):
        return '<span class="missing">–</span>'
    shown = format(float(value) * scale, spec)
    return (f'<data class="num" value="{float(value)!r}" data-source="{source}" data-key="{html.escape(key)}" '
            f'data-scale="{scale:g}" data-format="{spec}">{shown}</data>{unit}')


def _field(record: dict, source: str, key: str, spec: str, **options) -> str:
    """:func:`_num` of the value at ``key`` of ``record`` (from the file ``source``)."""
    return _num(_get(record, key), source, key, spec, **options)


def _png(data: bytes, alt: str) -> str:
    return (f'<img class="figure" alt="{html.escape(alt)}" '
            f'src="data:image/png;base64,{base64.b64encode(data).decode("ascii")}">')


def _asset(name: str) -> str:
    return (resources.files("fsswarp") / "data" / "report" / name).read_text(encoding="utf-8")


def _document(title: str, body: str, *, script: str = "") -> str:
    """The page: ``body`` with the style sheet and ``script`` inline; its Content-Security-Policy
    refuses every request (images are data URIs)."""
    policy = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta http-equiv="Content-Security-Policy" content="{policy}">\n'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f'<title>{html.escape(title)}</title>\n<style>\n{_asset("report.css")}</style>\n</head>\n'
            f'<body>\n<main>\n{body}\n</main>\n' + (f"<script>\n{script}</script>\n" if script else "")
            + "</body>\n</html>\n")


def _page(folder: Path, result: dict, dataset, meshes: dict, figures: dict, skipped: dict, *, name: str,
          command: str, backend, stages: dict) -> str:
    """The HTML of one reconstruction's report."""
    parts = [f"<h1>{html.escape(name)}: reconstruction report</h1>",
             f'<p class="lead">The sonar\'s depth D and tilt β and the object\'s shape, estimated from '
             f'{len(dataset.rig.names)} views by <code>fsswarp reconstruct</code> '
             f'(carving, then alternating pose and shape steps).</p>',
             _answer(result, dataset),
             "<h2>Per iteration</h2>",
             '<p class="note">Iteration 0 is the carved model at the start. The kept iteration has the '
             "lowest image error E_I; shaded bands are the intervals of D and β where result.json has them.</p>",
             _png(figures["history"], "depth, tilt and errors per iteration"),
             _history_table(result),
             _views(dataset, figures, skipped),
             _viewer(meshes, result),
             _made(folder, result, dataset, command, backend, stages)]
    return _document(f"{name}: reconstruction report", "\n".join(parts), script=_asset("viewer.js"))


def _answer(result: dict, dataset) -> str:
    """The answer first: D and β beside the start, the sensors and the truth; the errors."""
    manifest = dataset.manifest
    surface, truth = manifest.surface, manifest.truth
    if surface is None:  # deep water: the depth and tilt are known, not measured
        return _known_answer(result)
    sensors = {"surface": {"depth_m": surface.depth, "tilt_deg": math.degrees(surface.tilt),
                           "depth_sigma_m": surface.depth_sigma, "tilt_sigma_deg": math.degrees(surface.tilt_sigma)}}
    if truth is not None and truth.depth is not None:
        sensors["truth"] = {"depth_m": truth.depth, "tilt_deg": math.degrees(truth.tilt)}
    start_key = "start" if isinstance(result.get("start"), dict) else "history[0]"
    identified = result.get("identified") if isinstance(result.get("identified"), dict) else {}
    rows = []
    for label, key, spec, unit, scale_error, error_spec, error_unit in (
            ("depth D", "depth_m", ".3f", " m", 1000.0, "+.1f", " mm"),
            ("tilt β", "tilt_deg", ".2f", "°", 1.0, "+.2f", "°")):
        interval_key = key.replace("_", "_interval_", 1)
        if _interval(result, interval_key) is not None:
            interval = (f"[{_field(result, 'result.json', interval_key + '[0]', spec)}, "
                        f"{_field(result, 'result.json', interval_key + '[1]', spec)}]{unit}")
        else:
            interval = '<span class="missing">–</span>'
        flag = identified.get(key.split("_")[0])
        if isinstance(flag, bool):
            interval += (' <span class="badge yes">identified</span>' if flag else
                         ' <span class="badge no">not identified</span>')
        sigma = key.replace("_", "_sigma_", 1)
        measured = (f"{_field(sensors, 'dataset.toml', 'surface.' + key, spec)} ± "
                    f"{_field(sensors, 'dataset.toml', 'surface.' + sigma, spec)}{unit}")
        cells = [f'<td class="name">{label}</td>', f'<td class="big">{_field(result, "result.json", key, spec)}{unit}</td>',
                 f"<td>{interval}</td>", f"<td>{_field(result, 'result.json', start_key + '.' + key, spec)}{unit}</td>",
                 f"<td>{measured}</td>"]
        if "truth" in sensors:
            if isinstance(result.get("error_vs_truth"), dict):
                error = _field(result, "result.json", f"error_vs_truth.{key}", error_spec, scale=scale_error,
                               unit=error_unit)
            else:
                error = _num(result[key] - sensors["truth"][key], "computed", f"{key} - truth.{key}", error_spec,
                             scale=scale_error, unit=error_unit)
            cells += [f"<td>{_field(sensors, 'dataset.toml', 'truth.' + key, spec)}{unit}</td>", f"<td>{error}</td>"]
        rows.append("<tr>" + "".join(cells) + "</tr>")
    head = ("<tr><th class='name'></th><th>estimate</th><th>interval</th><th>start</th>"
            "<th>sensors (dataset.toml, ± 1σ)</th>" + ("<th>truth</th><th>error</th>" if "truth" in sensors else "")
            + "</tr>")
    extra = ""
    if isinstance(result.get("valley"), dict):
        extra = (f'<p class="note">Valley of the pose search (D − L·β): slope '
                 f'{_field(result, "result.json", "valley.slope_m_per_deg", ".1f", scale=1000.0, unit=" mm/°")}; '
                 f'at the estimated tilt it puts D at '
                 f'{_field(result, "result.json", "valley.depth_m_at_estimated_tilt", ".3f", unit=" m")}.</p>')
    start_source = "given on the command line" if start_key == "start" and _differs(result, surface) else "measured"
    return ("<h2>The answer</h2>\n"
            f'<table class="answer">{head}{"".join(rows)}</table>\n'
            f'<p class="note">Start: where the loop began ({start_source}). Intervals and identification come '
            f"from result.json where it has them.</p>\n{extra}{_cards(result)}")


def _known_answer(result: dict) -> str:
    """The answer of a deep-water dataset: the known D and β (no pose step), and the errors."""
    return ("<h2>The answer</h2>\n"
            f'<p>Deep water (no sea surface in view): the depth D = {_field(result, "result.json", "depth_m", ".3f")} m '
            f'and tilt β = {_field(result, "result.json", "tilt_deg", ".2f")}° are known (dataset.toml [rig]), '
            "not estimated; only the shape is.</p>\n" + _cards(result))


def _cards(result: dict) -> str:
    """The iterations, the image error and, with a truth model, E_V, Chamfer and F-score."""
    best = result["best_iteration"]
    kept = f"history[{best}]"
    cards = [_card("iterations", _field(result, "result.json", "iterations", ".0f"),
                   f"kept: {_field(result, 'result.json', 'best_iteration', '.0f')}; "
                   + ("converged" if result.get("converged") else "stopped at the iteration limit")),
             _card("image error E_I", _field(result, "result.json", f"{kept}.E_I", ".3f"), "1 = the carved model")]
    if "E_V" in result["history"][best]:
        cards += [_card("volume error E_V", _field(result, "result.json", f"{kept}.E_V", ".3f"),
                        f"carved: {_field(result, 'result.json', 'history[0].E_V', '.3f')}; 0 = the truth"),
                  _card("Chamfer", _field(result, "result.json", f"{kept}.chamfer_m", ".1f", scale=1000.0, unit=" mm"),
                        f"carved: {_field(result, 'result.json', 'history[0].chamfer_m', '.1f', scale=1000.0)} mm"),
                  _card("F-score", _field(result, "result.json", f"{kept}.fscore", ".3f"),
                        f"carved: {_field(result, 'result.json', 'history[0].fscore', '.3f')}; 1 at best")]
    cards.append(_card("reconstruction time", _field(result, "result.json", "seconds", ".1f", unit=" s"),
                       html.escape(f"{result['backend']} on {result['device']}")))
    return f'<div class="cards">{"".join(cards)}</div>'



def _differs(result: dict, surface) -> bool:
    """Whether result.json's start differs from the sensors' values (a given start)."""
    start = result["start"]
    return not (math.isclose(float(start.get("depth_m", surface.depth)), surface.depth, abs_tol=1e-9)
                and math.isclose(float(start.get("tilt_deg", math.degrees(surface.tilt))),
                                 math.degrees(surface.tilt), abs_tol=1e-9))


def _card(label: str, value: str, detail: str = "") -> str:
    return (f'<div class="card"><div class="label">{label}</div><div class="value">{value}</div>'
            + (f'<div class="detail">{detail}</div>' if detail else "") + "</div>")


#: The history table's columns: heading, key, format, scale.
HISTORY_COLUMNS = (("iteration", "iteration", ".0f", 1.0), ("D (m)", "depth_m", ".3f", 1.0),
                   ("β (°)", "tilt_deg", ".2f", 1.0), ("E_mu (mm)", "E_mu", ".1f", 1000.0),
                   ("AIE", "AIE", ".3f", 1.0), ("ACE (mm)", "ACE", ".2f", 1000.0), ("E_I", "E_I", ".3f", 1.0),
                   ("E_V", "E_V", ".3f", 1.0), ("Chamfer (mm)", "chamfer_m", ".1f", 1000.0),
                   ("F-score", "fscore", ".3f", 1.0))


def _history_table(result: dict) -> str:
    history = result["history"]
    columns = [c for c in HISTORY_COLUMNS if any(c[1] in h for h in history)]
    intervals = [(label, key, spec) for label, key, spec in (("D interval (m)", "depth_interval_m", ".3f"),
                                                             ("β interval (°)", "tilt_interval_deg", ".2f"))
                 if any(_interval(h, key) for h in history)]
    head = "".join(f"<th>{label}</th>" for label, *_ in columns) + "".join(f"<th>{label}</th>" for label, *_ in intervals)
    rows = []
    for i, entry in enumerate(history):
        cells = [f"<td>{_field(result, 'result.json', f'history[{i}].{key}', spec, scale=scale)}</td>"
                 for _, key, spec, scale in columns]
        for _, key, spec in intervals:
            cells.append("<td>" + (f"[{_field(result, 'result.json', f'history[{i}].{key}[0]', spec)}, "
                                   f"{_field(result, 'result.json', f'history[{i}].{key}[1]', spec)}]"
                                   if _interval(entry, key) else '<span class="missing">–</span>') + "</td>")
        style = ' class="kept"' if i == result["best_iteration"] else ""
        rows.append(f"<tr{style}>{''.join(cells)}</tr>")
    return f'<div class="scroll"><table class="history"><tr>{head}</tr>{"".join(rows)}</table></div>'


def _views(dataset, figures: dict, skipped: dict) -> str:
    """Per view the figure of data | ghost-free | carved | final, optimized views first."""
    parts = ["<h2>Views</h2>",
             '<p class="note">Like the paper\'s Figures 10–14: the data, the data with the ghost removed by the '
             "final model, and the synthetic views of the carved model (at the start) and of the final model (at "
             "the estimate), scaled to the data's level. Fan images: range arcs in metres, azimuth in degrees; "
             "each row in dB below its data's peak.</p>"]
    for group, optimize in (("Optimized views", True), ("Held-out views (not used by the pose and shape steps)", False)):
        views = [v for v in dataset.rig.views if v.optimize is optimize and v.name in figures]
        if not views:
            continue
        parts.append(f"<h3>{group}</h3>")
        for view in views:
            x, y = view.position
            parts.append(f'<figure class="view" id="view-{html.escape(view.name)}"><figcaption><b>'
                         f"{html.escape(view.name)}</b>: roll {math.degrees(view.roll):.1f}°, heading "
                         f"{math.degrees(view.heading):.1f}°, position ({x:.2f}, {y:.2f}) m</figcaption>"
                         + _png(figures[view.name], f"view {view.name}: data, ghost-free data, carved and final "
                                                    "model") + "</figure>")
    if skipped:
        parts.append('<p class="note">Not shown: ' + "; ".join(f"{html.escape(v)} ({html.escape(why)})"
                                                             for v, why in skipped.items()) + "</p>")
    return "\n".join(parts)


def _viewer(meshes: dict, result: dict) -> str:
    """The 3-D view: a canvas, its legend and the meshes' data for viewer.js."""
    from .figures import MODEL_COLOURS

    labels = {"carved": "carved model (iteration 0)", "final": f"final model (iteration {result['best_iteration']})",
              "truth": "truth"}
    points = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes.values()])
    low, high = points.min(axis=0), points.max(axis=0)
    span = np.where(high > low, high - low, 1.0)
    entries, legend = [], []
    for key, mesh in meshes.items():
        quantized = np.round((np.asarray(mesh.vertices) - low) / span * 65535).astype("<u2")
        wide = len(mesh.vertices) > 65535
        colour = [int(MODEL_COLOURS[key][i:i + 2], 16) / 255 for i in (1, 3, 5)]
        entries.append({"label": key, "colour": colour, "index_bytes": 4 if wide else 2,
                        "positions": base64.b64encode(quantized.tobytes()).decode("ascii"),
                        "indices": base64.b64encode(np.asarray(mesh.faces).astype("<u4" if wide else "<u2")
                                                    .tobytes()).decode("ascii")})
        legend.append(f'<label><input type="checkbox" checked data-mesh="{key}"><span class="swatch" '
                      f'style="background:{MODEL_COLOURS[key]}"></span>{labels[key]}: {len(mesh.faces):,} '
                      f"triangles, {abs(float(mesh.volume)) * 1e6:.0f} cm³</label>")
    data = json.dumps({"box": {"min": low.tolist(), "max": high.tolist()}, "meshes": entries}).replace("</", "<\\/")
    order = ", ".join(labels[k].split(" (")[0] for k in meshes)
    return ("<h2>3-D models</h2>\n"
            f'<div class="legend">{"".join(legend)}</div>\n'
            '<div class="legend"><button type="button" data-layout="side" aria-pressed="true">side by side</button>'
            '<button type="button" data-layout="overlay" aria-pressed="false">overlaid</button>'
            f'<span class="note">side by side, left to right: {order}. Axes from the models\' lowest corner: '
            "x red, y green (ahead of the sonar), z blue (up), reference frame in metres. Drag to turn, "
            "scroll to zoom, double-click to reset.</span></div>\n"
            '<canvas id="viewer" aria-label="3-D view of the models"></canvas>\n<p class="note" id="viewer-note"></p>\n'
            f'<script type="application/json" id="model-data">{data}</script>')


def _made(folder: Path, result: dict, dataset, command: str, backend, stages: dict) -> str:
    """How the reconstruction and this page were made."""
    versions = []
    for package in PACKAGES:
        try:
            versions.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{package} (not installed)")
    written = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    times = "".join(f"<li>{html.escape(stage)}: {seconds:.1f} s</li>" for stage, seconds in stages.items())
    rows = [("command", f"<code>{html.escape(command or 'fsswarp report')}</code>"),
            ("written", written),
            ("folder", f"<code>{html.escape(str(folder.resolve()))}</code>"),
            ("dataset", f"<code>{html.escape(str(dataset.root))}</code>"),
            ("reconstruction", html.escape(f"{result['backend']} on {result['device']}") + ", "
             + _field(result, "result.json", "seconds", ".1f", unit=" s") + " for the loop"),
            ("this page", html.escape(f"rendered with {backend.name} on {backend.device}") + f"<ul>{times}</ul>"),
            ("versions", html.escape(", ".join(versions) + f"; Python {platform.python_version()} on "
                                     f"{platform.system()} {platform.machine()}"))]
    return ("<h2>How it was made</h2>\n<dl class=\"made\">"
            + "".join(f"<dt>{label}</dt><dd>{value}</dd>" for label, value in rows) + "</dl>")


# --- a batch -----------------------------------------------------------------------------------

#: The batch table's numbers: heading, key in the job's result.json, format, scale.
BATCH_COLUMNS = (("D (m)", "depth_m", ".3f", 1.0), ("β (°)", "tilt_deg", ".2f", 1.0),
                 ("iterations", "iterations", ".0f", 1.0))
#: The batch table's numbers of the kept iteration: heading, key in its history entry, format, scale.
BATCH_KEPT = (("E_I", "E_I", ".3f", 1.0), ("E_V", "E_V", ".3f", 1.0), ("Chamfer (mm)", "chamfer_m", ".1f", 1000.0),
              ("F-score", "fscore", ".3f", 1.0))


def write_batch_report(folder, *, backend=None, command: str = "", drawer=None) -> Path:
    """Write DIR/report.html for the batch folder DIR (jobs.jsonl, DIR/<job>/): one row per job
    with its status, D and β (with their intervals where result.json has them), E_I and the
    truth scores, linked to the job's page, which is written first where it is missing and
    the job's dataset is known (``write_report``; a job whose page cannot be written says
    why in its row). Returns the path."""
    folder = Path(folder)
    jobs = _read_jobs(folder / JOBS_FILE)
    rows = []
    for job in jobs:
        rows.append(_batch_row(folder, job, backend=backend, command=command, drawer=drawer))
    ok = sum(job.get("status") == "ok" for job in jobs)
    head = ("<tr><th class='name'>job</th><th>status</th>"
            + "".join(f"<th>{label}</th>" for label, *_ in BATCH_COLUMNS[:2])
            + "<th>D interval (m)</th><th>β interval (°)</th>"
            + "".join(f"<th>{label}</th>" for label, *_ in BATCH_COLUMNS[2:] + BATCH_KEPT)
            + "<th>time (s)</th><th class='name'>where</th><th class='name'>note</th></tr>")
    body = (f"<h1>{html.escape(folder.name)}: batch report</h1>\n"
            f'<p class="lead">{len(jobs)} jobs of <code>fsswarp batch</code>, {ok} done; each job\'s name links '
            "to its reconstruction report.</p>\n"
            f'<div class="scroll"><table class="batch">{head}{"".join(rows)}</table></div>\n'
            f'<p class="note">Written {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M UTC} by '
            f"<code>{html.escape(command or 'fsswarp report')}</code>.</p>")
    return write_text(folder / REPORT_FILE, _document(f"{folder.name}: batch report", body))


def _read_jobs(path: Path) -> list[dict]:
    """The outcomes of jobs.jsonl, one per line (InputError naming the line otherwise)."""
    jobs = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            job = json.loads(line)
        except json.JSONDecodeError as err:
            raise InputError(f"not a JSON line: {err}", file=path, field=f"line {number}") from None
        if not isinstance(job, dict) or not isinstance(job.get("name"), str) or not job["name"]:
            raise InputError("must be a JSON object with a job name", file=path, field=f"line {number}")
        if "/" in job["name"] or job["name"].startswith("."):
            raise InputError("is not a job folder's name", file=path, field=f"line {number}.name", value=job["name"])
        jobs.append(job)
    return jobs


def _batch_row(folder: Path, job: dict, *, backend, command: str, drawer) -> str:
    """One job's row; writes the job's page first where it is missing."""
    name = job["name"]
    job_folder = folder / name
    notes = [job["error"]] if job.get("error") else []
    result = None
    if (job_folder / DONE_MARKER).is_file():
        try:
            result = read_result(job_folder / RESULT_FILE)
            if not (job_folder / REPORT_FILE).is_file():
                write_report(job_folder, backend=backend, command=command, drawer=drawer)
        except InputError as err:
            notes.append(f"no report: {err}")
    link = (f'<a href="{html.escape(name)}/{REPORT_FILE}">{html.escape(name)}</a>'
            if (job_folder / REPORT_FILE).is_file() else html.escape(name))
    source = f"{name}/{RESULT_FILE}"
    cells = [f'<td class="name">{link}</td>', f"<td>{html.escape(str(job.get('status', '')))}</td>"]
    record = result or {}
    for _, key, spec, scale in BATCH_COLUMNS[:2]:
        cells.append(f"<td>{_field(record, source, key, spec, scale=scale)}</td>")
    for key, spec in (("depth_interval_m", ".3f"), ("tilt_interval_deg", ".2f")):
        cells.append("<td>" + (f"[{_field(record, source, key + '[0]', spec)}, {_field(record, source, key + '[1]', spec)}]"
                               if _interval(record, key) else '<span class="missing">–</span>') + "</td>")
    for _, key, spec, scale in BATCH_COLUMNS[2:]:
        cells.append(f"<td>{_field(record, source, key, spec, scale=scale)}</td>")
    kept = f"history[{record['best_iteration']}]" if result else "history[0]"
    for _, key, spec, scale in BATCH_KEPT:
        cells.append(f"<td>{_field(record, source, f'{kept}.{key}', spec, scale=scale)}</td>")
    cells.append(f"<td>{_num(job.get('seconds'), JOBS_FILE, f'{name}.seconds', '.1f')}</td>")
    where = " ".join(str(job[k]) for k in ("node", "device") if job.get(k))
    cells += [f'<td class="name">{html.escape(where)}</td>', f'<td class="name">{html.escape("; ".join(notes))}</td>']
    return "<tr>" + "".join(cells) + "</tr>"
