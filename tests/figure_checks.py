"""Checks of the figures that fsswarp.figures writes: the figure objects kept for inspection,
and their layout (texts inside the figure and apart)."""


def captured_figures(monkeypatch):
    """The figures that fsswarp.figures writes (``write_figure``, which ``save_figure`` calls
    after its layout), kept for inspection."""
    import fsswarp.figures as figures

    kept, write = [], figures.write_figure

    def keep(fig, path, **options):
        kept.append(fig)
        return write(fig, path, **options)

    monkeypatch.setattr(figures, "write_figure", keep)
    return kept


def assert_laid_out(fig) -> None:
    """Each axes of ``fig`` (a figure laid out on a fixed grid, no tight bounding box to crop
    it) with all it draws (tick labels, titles, texts) lies inside the figure and clear of every
    other axes' box; so do the figure's title and legends; no two titles overlap, and an axis's
    tick labels keep 2 pixels apart."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()  # the figure is closed: a canvas of its own, same layout
    fig.draw(renderer)
    page = fig.bbox
    areas = {ax: ax.get_window_extent(renderer) for ax in fig.axes}
    extents = [(ax, ax.get_tightbbox(renderer)) for ax in fig.axes]
    extents += [(None, artist.get_window_extent(renderer)) for artist in [fig._suptitle, *fig.legends] if artist]
    for owner, box in extents:
        assert not any(box.overlaps(area) for other, area in areas.items() if other is not owner), owner
        assert page.x0 - 1 <= box.x0 and box.x1 <= page.x1 + 1 and page.y0 - 1 <= box.y0 and box.y1 <= page.y1 + 1, \
            (owner, box, page)
    for ax in fig.axes:
        for text in [ax.title, *ax.texts, ax.xaxis.label, ax.yaxis.label]:
            if text.get_visible() and text.get_text():
                box = text.get_window_extent(renderer)
                assert not any(box.overlaps(area) for other, area in areas.items() if other is not ax), text.get_text()
        for axis, side in ((ax.xaxis, 0), (ax.yaxis, 1)):  # the tick labels drawn, apart from each other
            area = areas[ax].get_points()[:, side]
            shown = [box for box in (t.get_window_extent(renderer) for t in axis.get_ticklabels() if t.get_text())
                     if area[0] - 1 <= box.get_points()[:, side].mean() <= area[1] + 1]
            for k, first in enumerate(shown):  # with a gap: labels that touch read as one number
                assert not any(first.padded(2).overlaps(second) for second in shown[k + 1:]), [
                    t.get_text() for t in axis.get_ticklabels()]
    titles = [ax.title.get_window_extent(renderer) for ax in fig.axes if ax.get_title()]
    if fig._suptitle is not None:
        titles.append(fig._suptitle.get_window_extent(renderer))
    for k, first in enumerate(titles):
        assert not any(first.overlaps(second) for second in titles[k + 1:])
