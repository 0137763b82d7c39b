"""``fsswarp report``: the page of a reconstruction and of a batch, checked as files and in a
real headless browser (Debian's Chromium driven by Playwright; .ci/browser installs it)."""

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from html.parser import HTMLParser
from pathlib import Path

import pytest

#: The keys the lead's sensor fusion adds to result.json, as the fixture sets them.
FUSION_KEYS = ("depth_interval_m", "tilt_interval_deg", "valley", "identified", "start", "error_vs_truth")


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", *args], capture_output=True,
                          text=True)


@pytest.fixture(scope="module")
def reconstruction(coral_south, tmp_path_factory):
    """One low-resolution reconstruction of coral-one seen from the south, written by the command
    line: (folder, stdout)."""
    out = tmp_path_factory.mktemp("report") / "rec"
    done = run_cli("reconstruct", str(coral_south.root), "--out", str(out), "--iterations", "0", "--resolution", "32")
    assert done.returncode == 0, done.stderr
    return out, done.stdout


def copy_with(folder: Path, target: Path, change) -> Path:
    """A copy of the reconstruction ``folder`` at ``target`` without its page, its result.json
    changed by ``change(result)``."""
    shutil.copytree(folder, target)
    (target / "report.html").unlink()
    result = json.loads((target / "result.json").read_text())
    change(result)
    (target / "result.json").write_text(json.dumps(result, indent=2))
    return target


def add_fusion_keys(result: dict) -> None:
    """The sensor-fusion keys, set to values of our own around the real estimate."""
    depth, tilt = result["depth_m"], result["tilt_deg"]
    result.update(depth_interval_m=[depth - 0.0123, depth + 0.0087], tilt_interval_deg=[tilt - 0.4449, tilt + 0.3151],
                  valley={"slope_m_per_deg": 0.03456, "depth_m_at_estimated_tilt": depth + 0.00111},
                  identified={"depth": False, "tilt": True}, start={"depth_m": 0.4321, "tilt_deg": 9.876},
                  error_vs_truth={"depth_m": 0.02345, "tilt_deg": -0.5678})
    for k, entry in enumerate(result["history"]):
        entry["depth_interval_m"] = [entry["depth_m"] - 0.01 - 0.001 * k, entry["depth_m"] + 0.01]
        entry["tilt_interval_deg"] = [entry["tilt_deg"] - 0.3, entry["tilt_deg"] + 0.2 + 0.01 * k]


def drop_fusion_keys(result: dict) -> None:
    for key in FUSION_KEYS:
        result.pop(key, None)
    for entry in result["history"]:
        entry.pop("depth_interval_m", None)
        entry.pop("tilt_interval_deg", None)


@pytest.fixture(scope="module")
def variants(reconstruction, coral_south, tmp_path_factory):
    """The reconstruction's own page, and pages of copies with the fusion keys (written by
    ``fsswarp report OUT --dataset DIR``) and without them (by ``fsswarp.report.report``):
    {name: folder}."""
    from fsswarp.backends import get_backend
    from fsswarp.report import report

    folder, _ = reconstruction
    root = tmp_path_factory.mktemp("variants")
    target = copy_with(folder, root / "with", add_fusion_keys)
    done = run_cli("report", str(target), "--dataset", str(coral_south.root))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"wrote {target / 'report.html'}"
    bare = copy_with(folder, root / "without", drop_fusion_keys)
    assert report(bare, dataset_dir=coral_south.root, backend=get_backend("opencl")) == bare / "report.html"
    return {"written by reconstruct": folder, "with the fusion keys": target, "without them": bare}


def test_a_page_finished_later_is_the_page_written_at_once(reconstruction, coral_south, tmp_path, monkeypatch):
    """``write_report(later=stack)`` writes nothing until the stack closes, then the page that
    ``write_report`` writes at once (all but "how it was made": times and folder); an error
    before the stack closes writes no page. Given the views enhanced already (``enhanced``, as
    the demo gives its enhancement), it shows them and enhances nothing again: the same page."""
    import math
    from contextlib import ExitStack

    import fsswarp.enhancement
    from fsswarp.backends import get_backend
    from fsswarp.dataset import read_mesh
    from fsswarp.figures import FigureDrawer
    from fsswarp.report import write_report

    folder, _ = reconstruction
    backend = get_backend("opencl")
    now, later_folder, failing = (copy_with(folder, tmp_path / name, lambda result: None)
                                  for name in ("now", "later", "failing"))
    write_report(now, dataset=coral_south, backend=backend, name="coral-one")
    result = json.loads((folder / "result.json").read_text())
    model = read_mesh(folder / "model.ply", field="model.ply")
    enhanced = fsswarp.enhancement.enhance(coral_south, model, result["depth_m"], math.radians(result["tilt_deg"]),
                                           backend=backend, model_name="the final model")

    def again(*args, **kwargs):
        raise AssertionError("enhanced again")

    monkeypatch.setattr(fsswarp.enhancement, "enhance", again)
    drawer = FigureDrawer(2)
    try:
        with ExitStack() as later:
            page = write_report(later_folder, dataset=coral_south, backend=backend, name="coral-one", drawer=drawer,
                                later=later, enhanced=enhanced)
            assert page == later_folder / "report.html" and not page.exists()
        with pytest.raises(RuntimeError, match="stop"), ExitStack() as later:
            write_report(failing, dataset=coral_south, backend=backend, name="coral-one", drawer=drawer, later=later,
                         enhanced=enhanced)
            raise RuntimeError("stop")
    finally:
        drawer.close()
    assert not (failing / "report.html").exists()

    def without_made(path):
        return re.sub(r'<h2>How it was made</h2>.*?</dl>', "", path.read_text(), flags=re.S)

    assert "data:image/png;base64," in without_made(page) and without_made(page) == without_made(now / "report.html")


# --- the page as a file --------------------------------------------------------------------------

class Elements(HTMLParser):
    """Every start tag (name, attributes) and the text of each <data class="num">."""

    def __init__(self, text: str):
        super().__init__()
        self.tags, self.numbers, self._open = [], [], None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        self.tags.append((tag, attrs))
        if tag == "data" and attrs.get("class") == "num":
            self._open = dict(attrs, text="")

    def handle_data(self, data):
        if self._open is not None:
            self._open["text"] += data

    def handle_endtag(self, tag):
        if tag == "data" and self._open is not None:
            self.numbers.append(self._open)
            self._open = None


def test_reconstruct_writes_the_page_and_prints_its_path(reconstruction):
    folder, stdout = reconstruction
    assert f"report: {folder / 'report.html'}" in stdout.splitlines()
    assert (folder / "report.html").stat().st_size > 100_000


@pytest.mark.parametrize("name", ["written by reconstruct", "with the fusion keys", "without them"])
def test_the_page_holds_everything_it_shows(variants, name):
    """No address outside the page: every image a PNG data URI, the script and the style inline,
    and a Content-Security-Policy that refuses any request."""
    text = (variants[name] / "report.html").read_text()
    tags = Elements(text).tags
    images = [attrs["src"] for tag, attrs in tags if tag == "img"]
    assert len(images) >= 2 and all(src.startswith("data:image/png;base64,") for src in images)
    assert not [tag for tag, attrs in tags if tag in ("link", "iframe", "object", "embed") or
                (tag == "script" and "src" in attrs)]
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text)
    policy = [attrs["content"] for tag, attrs in tags if attrs.get("http-equiv") == "Content-Security-Policy"]
    assert policy and policy[0].startswith("default-src 'none'")


def resolve(record, key: str):
    """The value at a dotted key with [i] indices, e.g. history[1].E_V (the test's own parser)."""
    value = record
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", key):
        value = value[int(index)] if index else value[name]
    return value


def sources(folder: Path, dataset_root: Path) -> dict:
    return {"result.json": json.loads((folder / "result.json").read_text()),
            "dataset.toml": tomllib.loads((dataset_root / "dataset.toml").read_text())}


def expected_text(number: dict, files: dict) -> str:
    """What a <data class="num"> must show: its source's value at its key, scaled, formatted."""
    if number["data-source"] == "computed":
        first, second = number["data-key"].split(" - ")
        value = resolve(files["result.json"], first) - resolve(files["dataset.toml"], second)
    else:
        value = resolve(files[number["data-source"]], number["data-key"])
    return format(value * float(number["data-scale"]), number["data-format"])


@pytest.mark.parametrize("name", ["written by reconstruct", "with the fusion keys", "without them"])
def test_every_number_shown_is_the_file_s_rounded_as_declared(variants, coral_south, name):
    folder = variants[name]
    numbers = Elements((folder / "report.html").read_text()).numbers
    files = sources(folder, coral_south.root)
    for number in numbers:
        assert number["text"] == expected_text(number, files), number
    shown = {(n["data-key"], n["data-format"], n["data-scale"]) for n in numbers}
    best = files["result.json"]["best_iteration"]
    for key, spec, scale in (("depth_m", ".3f", "1"), ("tilt_deg", ".2f", "1"), ("iterations", ".0f", "1"),
                             (f"history[{best}].E_I", ".3f", "1"), (f"history[{best}].E_V", ".3f", "1"),
                             (f"history[{best}].chamfer_m", ".1f", "1000"), (f"history[{best}].fscore", ".3f", "1"),
                             ("surface.depth_m", ".3f", "1"), ("surface.tilt_deg", ".2f", "1"),
                             ("truth.depth_m", ".3f", "1"), ("truth.tilt_deg", ".2f", "1")):
        assert (key, spec, scale) in shown, key
    keys = {n["data-key"] for n in numbers}
    if name == "with the fusion keys":
        for key in ("depth_interval_m[0]", "depth_interval_m[1]", "tilt_interval_deg[0]", "tilt_interval_deg[1]",
                    "valley.slope_m_per_deg", "valley.depth_m_at_estimated_tilt", "start.depth_m", "start.tilt_deg",
                    "error_vs_truth.depth_m", "error_vs_truth.tilt_deg", "history[0].depth_interval_m[0]"):
            assert key in keys, key
        text = (folder / "report.html").read_text()
        assert text.count('class="badge no">not identified') == 1 and text.count('class="badge yes">identified') == 1
    if name == "without them":
        assert not any("interval" in key or key.startswith(("valley", "start", "error_vs_truth")) for key in keys)
        assert "depth_m - truth.depth_m" in keys  # the error, computed from the two files


# --- user mistakes ---------------------------------------------------------------------------

def test_a_folder_that_is_no_output_is_refused_and_nothing_is_written(coral_south, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    for folder, needle in ((tmp_path / "mine", "is neither a reconstruction output"),
                           (coral_south.root, "is neither a reconstruction output"),
                           (tmp_path / "nowhere", "no such folder"),
                           (tmp_path / "mine" / "notes.txt", "is not a folder")):
        before = sorted(p.name for p in tmp_path.rglob("*")) + sorted(p.name for p in coral_south.root.iterdir())
        done = run_cli("report", str(folder))
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0] and folder.name in lines[0], lines
        assert done.stdout == ""
        after = sorted(p.name for p in tmp_path.rglob("*")) + sorted(p.name for p in coral_south.root.iterdir())
        assert after == before


@pytest.mark.parametrize("change, needle", [
    (lambda r: r.pop("history"), "result.json: history"),
    (lambda r: r.update(best_iteration=7), "result.json: best_iteration = 7"),
    (lambda r: r.update(depth_m="deep"), "result.json: depth_m = 'deep'"),
    (None, "result.json: dataset: does not name the dataset folder it was made from; pass --dataset DIR"),
])
def test_a_broken_or_unplaced_reconstruction_is_one_line(reconstruction, tmp_path, change, needle):
    folder = copy_with(reconstruction[0], tmp_path / "rec", change or (lambda r: None))
    done = run_cli("report", str(folder))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in done.stderr, lines
    assert not (folder / "report.html").exists()


# --- a batch ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def batch_folder(reconstruction, coral_south, tmp_path_factory):
    """A batch folder as fsswarp batch writes it: job "a" with its page, job "c" without one
    (its result.json names its dataset), job "b" failed. ``fsswarp report DIR`` has run."""
    folder = tmp_path_factory.mktemp("batch") / "runs"
    folder.mkdir()
    shutil.copytree(reconstruction[0], folder / "a")
    copy_with(reconstruction[0], folder / "c", lambda r: r.update(dataset=str(coral_south.root)))
    jobs = [{"name": "a", "status": "ok", "attempts": 1, "seconds": 31.25, "error": None, "node": "n1", "device": "cpu"},
            {"name": "b", "status": "failed", "attempts": 1, "seconds": 0.5, "error": "dataset.toml: no such file",
             "node": "n1", "device": "cpu"},
            {"name": "c", "status": "ok", "attempts": 2, "seconds": 40.75, "error": None, "node": "n2", "device": "cpu"}]
    (folder / "jobs.jsonl").write_text("".join(json.dumps(job) + "\n" for job in jobs))
    done = run_cli("report", str(folder))
    assert done.returncode == 0, done.stderr
    return folder


def test_a_batch_page_has_a_row_per_job_linked_to_its_page(batch_folder):
    text = (batch_folder / "report.html").read_text()
    assert (batch_folder / "c" / "report.html").is_file()  # written because it was missing
    links = [attrs["href"] for tag, attrs in Elements(text).tags if tag == "a"]
    assert links == ["a/report.html", "c/report.html"]
    assert "dataset.toml: no such file" in text
    jobs = {json.loads(line)["name"]: json.loads(line) for line in (batch_folder / "jobs.jsonl").read_text().splitlines()}
    numbers = Elements(text).numbers
    for number in numbers:
        source = number["data-source"]
        value = resolve(jobs, number["data-key"]) if source == "jobs.jsonl" else \
            resolve(json.loads((batch_folder / source).read_text()), number["data-key"])
        assert number["text"] == format(value * float(number["data-scale"]), number["data-format"]), number
    assert {n["data-key"] for n in numbers if n["data-source"] == "a/result.json"} >= {"depth_m", "tilt_deg"}


# --- in a real browser -----------------------------------------------------------------------------

def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium (Debian's) driven by Playwright; skipped with the reason where either
    is missing, except in CI (CI=true), which installs both."""
    reason = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        reason = "Playwright is not installed (pip install -e '.[test]')"
    executable = find_chromium()
    if reason is None and executable is None:
        reason = "no Chromium here (bash .ci/browser installs Debian's)"
    if reason is not None:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the browser tests: {reason}")
        pytest.skip(reason)
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, args=["--enable-unsafe-swiftshader"])
        yield browser
        browser.close()


def open_page(browser, path: Path):
    """The page at ``path`` in a fresh offline context, loaded, with its 3-D view drawn; returns
    (page, what happened: requests, failed requests, console errors)."""
    context = browser.new_context(offline=True, viewport={"width": 1200, "height": 900})
    page = context.new_page()
    seen = {"requests": [], "failed": [], "errors": []}
    page.on("request", lambda request: seen["requests"].append(request.url))
    page.on("requestfailed", lambda request: seen["failed"].append(request.url))
    page.on("console", lambda message: seen["errors"].append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: seen["errors"].append(str(error)))
    page.goto(path.as_uri(), wait_until="load")
    return page, seen


def coloured_pixels(png: bytes) -> dict[str, int]:
    """How many pixels of the PNG are orange (the carved model's hue, shaded or not), blue (the
    final model's) and neither white nor grey (anything drawn)."""
    import io

    import numpy as np
    from PIL import Image

    r, g, b = np.moveaxis(np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), int), 2, 0)
    return {"orange": int(((r - b > 60) & (r >= g)).sum()), "blue": int(((b - r > 50) & (b >= g)).sum()),
            "drawn": int((np.maximum(np.maximum(r, g), b) < 235).sum())}


@pytest.mark.parametrize("name", ["written by reconstruct", "with the fusion keys", "without them"])
def test_the_page_in_a_browser(browser, variants, coral_south, name):
    folder = variants[name]
    page, seen = open_page(browser, folder / "report.html")
    # a selector, not wait_for_function: its polling evaluates a string, which the page's CSP forbids
    page.wait_for_selector("#viewer[data-state='drawn']", state="attached", timeout=30_000)
    assert seen["failed"] == [] and seen["errors"] == [], seen
    assert [url for url in seen["requests"] if not url.startswith("data:")] == [(folder / "report.html").as_uri()]
    images = page.eval_on_selector_all("img", "all => all.map(i => [i.complete, i.naturalWidth, i.naturalHeight])")
    assert len(images) >= 2 and all(done and width > 0 and height > 0 for done, width, height in images), images
    assert page.eval_on_selector("#viewer", "c => c.dataset.meshesDrawn") == "3"
    pixels = coloured_pixels(page.locator("#viewer").screenshot())
    assert pixels["orange"] > 2000 and pixels["blue"] > 2000 and pixels["drawn"] > 3 * (2000 + 2000), pixels
    page.uncheck("input[data-mesh=carved]")  # the legend's box hides the carved model
    hidden = coloured_pixels(page.locator("#viewer").screenshot())
    assert hidden["orange"] < pixels["orange"] / 50 and hidden["blue"] > 2000, hidden
    assert page.eval_on_selector("#viewer", "c => c.dataset.meshesDrawn") == "2"
    files = sources(folder, coral_south.root)
    shown = page.eval_on_selector_all("data.num", """all => all.map(e => ({"data-source": e.dataset.source,
        "data-key": e.dataset.key, "data-scale": e.dataset.scale, "data-format": e.dataset.format,
        "text": e.textContent}))""")
    assert len(shown) > 20
    for number in shown:
        assert number["text"] == expected_text(number, files), number
    assert seen["errors"] == []
    page.context.close()


def test_the_batch_page_in_a_browser(browser, batch_folder):
    page, seen = open_page(browser, batch_folder / "report.html")
    assert seen["failed"] == [] and seen["errors"] == [], seen
    rows = page.eval_on_selector_all("table.batch tr", "rows => rows.length")
    assert rows == 4  # the heading and three jobs
    page.click("a[href='c/report.html']")
    page.wait_for_selector("#viewer[data-state]", state="attached", timeout=30_000)
    assert page.url == (batch_folder / "c" / "report.html").as_uri()
    assert page.eval_on_selector("#viewer", "c => c.dataset.state") == "drawn"
    assert seen["failed"] == [] and seen["errors"] == [], seen
    page.context.close()


def test_the_numbers_are_rounded_to_what_they_mean(variants):
    """D in mm (three decimals of a metre) and β in hundredths of a degree, as a person reads them."""
    text = (variants["with the fusion keys"] / "report.html").read_text()
    result = json.loads((variants["with the fusion keys"] / "result.json").read_text())
    assert f">{result['depth_m']:.3f}</data> m" in text and f">{result['tilt_deg']:.2f}</data>°" in text
    assert f"{result['error_vs_truth']['depth_m'] * 1000:+.1f}</data> mm" in text
