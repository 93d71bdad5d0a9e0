"""Previews: pictures read back with Pillow, checked against where the orthographic camera must put things."""

import numpy as np
import pytest
from PIL import Image

from hairwarp.io.cache import CacheWriter
from hairwarp.preview import BACKGROUND, preview_cache, render_frames, scale_bar_label, scale_bar_length

BG_TOLERANCE = 12
"""Max per-channel difference [0-255] still counted as background (anti-aliased edges, PNG is lossless)."""
CENTRE_PX = 3
"""Allowed asymmetry of mirrored strands about the panel centre [px] (anti-aliasing and pixel snapping)."""

GIF_TICK_MS = 10
"""GIF frame delays are stored in hundredths of a second."""

BG = np.array([int(BACKGROUND[i : i + 2], 16) for i in (1, 3, 5)])


def _vertical_strands(xs, n_pts=12, top=0.0, length=0.3):
    """Straight strands hanging from z = top at the given x (y = 0): (points, curve_vertex_counts)."""
    z = np.linspace(top, top - length, n_pts)
    pts = np.concatenate([np.stack([np.full(n_pts, x), np.zeros(n_pts), z], axis=1) for x in xs])
    return pts, np.full(len(xs), n_pts)


def _octahedron(centre, r):
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float) * r + centre
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


def _foreground(path):
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    return img, np.abs(img - BG).max(axis=2) > BG_TOLERANCE


def _hair_mask(img):
    """Hair is brown: clearly more red than blue; the grey mesh and the background are not."""
    return (img[..., 0] - img[..., 2]) > 25


def test_render_frames_size_and_hair_pixels(tmp_path):
    out = render_frames([{"hair": _vertical_strands([-0.1, 0.1])}], tmp_path / "sheet.png", view="front",
                        size_px=(400, 300))
    img, fg = _foreground(out)
    assert Image.open(out).size == (400, 300)
    hair = _hair_mask(img) & fg
    assert hair.sum() > 200, "too few hair pixels"
    # Front view, orthographic, limits centred on the data: the two strands sit symmetrically about the centre.
    cols = np.flatnonzero(hair.any(axis=0))
    left, right = cols[cols < 200], cols[cols >= 200]
    assert len(left) and len(right)
    assert abs((200 - left.mean()) - (right.mean() - 200)) < CENTRE_PX
    # The strands are vertical: hair pixels in a column span most of the panel height.
    assert hair[:, int(round(left.mean()))].sum() > 150


def test_scale_bar_is_a_round_length_drawn_to_the_strands_scale(tmp_path):
    """The first panel's scale bar: 1, 2 or 5 times a power of ten metres, at most a sixth of the panel, and as many
    pixels per metre as the two strands 0.2 m apart are (the camera is orthographic)."""
    for span, length, label in ((0.6, 0.1, "10 cm"), (0.35, 0.05, "5 cm"), (1.2, 0.2, "20 cm"), (3.0, 0.5, "50 cm"),
                                (0.012, 0.002, "2 mm"), (7.0, 1.0, "1 m")):
        assert scale_bar_length(span) == pytest.approx(length) and scale_bar_label(length) == label
    out = render_frames([{"hair": _vertical_strands([-0.1, 0.1])}], tmp_path / "sheet.png", view="front",
                        size_px=(600, 400))
    img, fg = _foreground(out)
    hair = _hair_mask(img) & fg
    cols = np.flatnonzero(hair.any(axis=0))
    strands_px = cols[cols >= 300].mean() - cols[cols < 300].mean()  # 0.2 m
    grey = fg & ~_hair_mask(img) & (np.abs(img - 107).max(axis=2) < 40)  # the caption colour, #6b6b6b
    lower_left = grey[200:, :300]
    row = int(np.argmax(lower_left.sum(axis=1)))
    bar = np.flatnonzero(lower_left[row])
    bar_m = 0.2 * (bar[-1] - bar[0]) / strands_px
    # one pixel of anti-aliasing at each end of the bar, of about 50 px
    assert any(abs(bar_m - m) < 0.04 * m for m in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)), bar_m


def test_same_camera_in_every_panel_and_meshes(tmp_path):
    a = _vertical_strands([0.0])
    b = (a[0] + [0.2, 0.0, 0.0], a[1])  # the second frame moved 0.2 m along +x
    mesh = _octahedron(np.array([0.0, 0.0, 0.05]), 0.05)
    out = render_frames([{"hair": a}, {"hair": b}], tmp_path / "two.png", meshes=[mesh, mesh], view="front",
                        size_px=(800, 400), titles=["first", "second"])
    img, fg = _foreground(out)
    hair = _hair_mask(img) & fg
    half = img.shape[1] // 2
    x1 = np.flatnonzero(hair[:, :half].any(axis=0)).mean()
    x2 = np.flatnonzero(hair[:, half:].any(axis=0)).mean()
    # Same limits in both panels: the strand is to the right in the second panel, the mesh is not.
    assert x2 - x1 > 40
    grey = fg & ~_hair_mask(img) & (np.ptp(img, axis=2) < 12) & (img.mean(axis=2) < 225)
    g1 = np.flatnonzero(grey[:300, :half].any(axis=0)).mean()
    g2 = np.flatnonzero(grey[:300, half:].any(axis=0)).mean()
    assert grey[:300].sum() > 500, "mesh not drawn"
    assert abs(g2 - g1) < CENTRE_PX


def _tiny_cache(path, frames=3, start_frame=0):
    v, f = _octahedron(np.zeros(3), 0.05)
    with CacheWriter(path, fps=12, start_frame=start_frame) as cache:
        cache.add_curves("dense", np.full(6, 10), basis="catmullRom")
        cache.add_curves("guides", np.full(2, 10), kind="guides")
        cache.add_mesh("head", v, f)
        for i in range(frames):
            pts, _ = _vertical_strands(np.linspace(-0.04, 0.04, 6), n_pts=10, top=0.05)
            pts[:, 1] += 0.02 * i * np.linspace(0, 1, 10)[np.arange(len(pts)) % 10]
            g, _ = _vertical_strands([-0.05, 0.05], n_pts=10, top=0.05)
            m = np.eye(4)
            m[0, 3] = 0.01 * i
            cache.write_frame(start_frame + i, {"dense": (pts, None), "guides": (g, None)}, xforms={"head": m})
    return path


def test_frames_are_captioned_by_time_code_and_time_from_the_start(tmp_path):
    """A cache whose frames start at 1001 (``output.start_frame``): its first frame is frame 1001 at 0 s, as the
    run's own preview captions it, and the next 1/12 s later (12 frames a second)."""
    from hairwarp.io.usd_inspect import read_frames
    from hairwarp.preview import frame_title

    data = read_frames(_tiny_cache(tmp_path / "late.usdc", start_frame=1001))
    assert [d["frame"] for d in data] == [1001.0, 1002.0, 1003.0]
    assert [d["time"] for d in data] == pytest.approx([0.0, 1 / 12, 2 / 12])
    assert frame_title(data[1]["frame"], data[1]["time"]) == "frame 1002   0.08 s"


def test_preview_cache_png(tmp_path):
    cache = _tiny_cache(tmp_path / "tiny.usdc")
    out = preview_cache(cache, frames=2)
    assert out == tmp_path / "tiny.png"
    img, fg = _foreground(out)
    assert fg.sum() > 500
    assert (_hair_mask(img) & fg).sum() > 100
    out2 = preview_cache(cache, tmp_path / "pics" / "one.png", frames=[1], view=(30.0, 20.0))
    assert Image.open(out2).format == "PNG"


def test_preview_cache_shows_what_renders_unless_asked_for_guides(tmp_path):
    """A cache with dense hair and guides: by default the sheet draws the dense hair alone, as the run's own preview
    does; with guides=True the two guide strands (outside the dense ones) add their pixels; a cache of guides alone
    shows them."""
    from hairwarp.preview import rendered_curves

    curves = {"dense": 1, "guides": 2}
    assert rendered_curves(curves) == {"dense": 1} and rendered_curves(curves, guides=True) == curves
    assert rendered_curves({"guides": 2}) == {"guides": 2}
    cache = _tiny_cache(tmp_path / "tiny.usdc")
    _, plain = _foreground(preview_cache(cache, tmp_path / "plain.png", frames=[0], view="front"))
    _, both = _foreground(preview_cache(cache, tmp_path / "both.png", frames=[0], view="front", guides=True))
    assert both.sum() > plain.sum() + 100


def test_preview_cache_gif(tmp_path):
    cache = _tiny_cache(tmp_path / "tiny.usda", frames=4)
    out = preview_cache(cache, gif=True)
    assert out == tmp_path / "tiny.gif"
    gif = Image.open(out)
    assert gif.format == "GIF"
    assert gif.n_frames == 4
    assert abs(gif.info["duration"] - 1000 / 12) <= GIF_TICK_MS


@pytest.mark.parametrize(("options", "name", "says"), [([], "y.jpg", "name the picture .png"),
                                                      ([], "y.gif", "add --gif"),
                                                      (["--gif"], "y2.png", "name the picture .gif")])
def test_preview_refuses_a_suffix_of_another_format(tmp_path, capsys, options, name, says):
    """The suffix of ``-o`` must name the format written, PNG (GIF with ``--gif``): a sheet to ``y.jpg`` and an
    animation to ``y2.png`` were written, in the other format, and exited 0. One line, exit 2, nothing written."""
    from hairwarp.cli import main

    cache = _tiny_cache(tmp_path / "tiny.usdc", frames=2)
    assert main(["preview", str(cache), *options, "-o", str(tmp_path / name)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / name) in err[0] and says in err[0], err
    assert not (tmp_path / name).exists()
    assert main(["preview", str(cache), *options, "-o", str(tmp_path / f"ok{'.GIF' if options else '.PNG'}")]) == 0


def test_preview_says_which_frames_it_cannot_show(tmp_path, capsys):
    """``--frames`` beyond a cache's frames, and ``--frames`` with ``--gif`` (which shows every frame), were dropped
    without a word: each is now one note on stderr, and the picture is written. Frames the cache has: no note."""
    from hairwarp.cli import main

    cache = _tiny_cache(tmp_path / "tiny.usdc", frames=3)
    assert main(["preview", str(cache), "--frames", "100", "-o", str(tmp_path / "a.png")]) == 0
    assert capsys.readouterr().err.splitlines() == [
        "hairwarp: note: the cache has 3 frames, fewer than --frames 100: the sheet shows all 3"]
    assert main(["preview", str(cache), "--gif", "--frames", "2", "-o", str(tmp_path / "a.gif")]) == 0
    assert capsys.readouterr().err.splitlines()[0] == (
        "hairwarp: note: --frames is for the contact sheet; the GIF shows every frame of the cache (3)")
    assert Image.open(tmp_path / "a.gif").n_frames == 3
    assert main(["preview", str(cache), "--frames", "2", "-o", str(tmp_path / "b.png")]) == 0
    assert capsys.readouterr().err == ""


def test_a_contact_sheet_of_many_frames_shows_at_most_its_panels(tmp_path, capsys):
    """A sheet is held to 2400 px: asked for 100 frames of a 30-frame cache it had no width left for a panel and
    failed with the imaging library's message. It shows ``MAX_SHEET_FRAMES``, evenly spaced, and says so."""
    from hairwarp.cli import main
    from hairwarp.preview import MAX_SHEET_FRAMES

    cache = _tiny_cache(tmp_path / "tiny.usdc", frames=30)
    assert main(["preview", str(cache), "--frames", "100", "-o", str(tmp_path / "a.png")]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"hairwarp: note: a contact sheet shows at most {MAX_SHEET_FRAMES} frames: {MAX_SHEET_FRAMES} of the cache's "
        "30, evenly spaced (--gif shows every frame)"]
    assert Image.open(tmp_path / "a.png").size == (2400, 600)


def test_preview_gif_shows_its_progress(tmp_path):
    """`hairwarp preview --gif` prints the frames drawn as `hairwarp run` prints its frames (a line per tenth when
    stderr is not a terminal), counted from 1: of 11 frames, 1/11 to 11/11 (a first 'frame 0/11' took the first
    tenth's line and 1/11 was never shown). The GIF it writes has every frame of the cache, as usd-core counts them."""
    import re
    import subprocess
    import sys

    from pxr import Usd

    cache = _tiny_cache(tmp_path / "tiny.usda", frames=11)
    stage = Usd.Stage.Open(str(cache))
    samples = int(stage.GetEndTimeCode() - stage.GetStartTimeCode()) + 1
    r = subprocess.run([sys.executable, "-m", "hairwarp", "preview", cache, "--gif"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.strip().splitlines()
    assert [line.split()[1] for line in lines] == [f"{i}/{samples}" for i in range(1, samples + 1)], lines
    # As in a run, the rate and the time left show once the clock has a frame to go by.
    assert all(re.fullmatch(rf"frame \d+/{samples}(  [\d.]+ frames/s  \d+ s left)?", line) for line in lines), lines
    assert Image.open(tmp_path / "tiny.gif").n_frames == samples


def test_grid_row_titles_stay_left_of_the_panels(tmp_path):
    """A row title with a wedged key in full (``head.motion.angular_velocity = [0, 0, 1]``, 230 px wide) widens
    the title column instead of running into the first panel (the column was 190 px whatever the titles)."""
    from hairwarp.preview import render_grid

    panel = 300
    title = "tiny_0\nhead.motion.angular_velocity = [0, 0, 1]\nok"
    _, ink = _foreground(render_grid([[None]], tmp_path / "grid.png", row_titles=[title], panel_px=(panel, panel)))
    column = ink.shape[1] - panel
    assert column > 230
    assert ink[:, :column].any() and not ink[:, column - 4 : column + 100].any()


@pytest.mark.parametrize("shared", [True, False])
def test_grid_scale_bars_one_for_a_shared_framing_one_a_row_otherwise(tmp_path, shared):
    """A wedge's grid (one framing) has one scale bar, in its first panel; a grid of shots framed row by row has
    one in each row's first panel (the rows' scales differ)."""
    from hairwarp.preview import GRID_HEADER_PX, render_grid

    frame = {"curves": {"hair": _vertical_strands([-0.1, 0.1])}}
    rows = [[frame, frame], [frame, frame]]
    out = render_grid(rows, tmp_path / "grid.png", row_titles=["a", "b"], panel_px=(300, 300),
                      shared_limits=shared)
    img, fg = _foreground(out)
    grey = fg & ~_hair_mask(img) & (np.abs(img - 107).max(axis=2) < 40)
    left = img.shape[1] - 2 * 300  # the title column

    def bar_in(r, c):  # the lower left quarter of panel (r, c): a horizontal grey run of 20 px or more
        top = GRID_HEADER_PX + r * 300 + 150
        quarter = grey[top:top + 150, left + c * 300:left + c * 300 + 150]
        return bool(quarter.sum(axis=1).max() >= 20)

    assert bar_in(0, 0) and not bar_in(0, 1) and not bar_in(1, 1)
    assert bar_in(1, 0) is (not shared)


def test_gif_frames_keep_the_frame_rate_to_a_hundredth_of_a_second():
    """GIF stores hundredths of a second: 30 frames at 30 fps last 3, 4, 3, ... hundredths, 1 s in all (a constant
    33 ms, stored as 30, played 10 % fast); 24 fps, 6 frames: 0.25 s."""
    from hairwarp.preview import gif_durations

    d = gif_durations(30, 30.0)
    assert sum(d) == 1000 and set(d) == {30, 40} and all(x % 10 == 0 for x in d)
    assert sum(gif_durations(6, 24.0)) == 250
