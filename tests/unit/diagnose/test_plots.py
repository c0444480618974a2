"""The diagnosis's ranking figure: its scale shows a flagged candidate beside a far stronger one."""

from types import SimpleNamespace

import numpy as np

from solderpyro.diagnose.plots import evidence_scale, plot_ranking

THR = -np.log10(0.01 / 7)  # the 1 % Bonferroni line of 7 candidates, 2.85


def test_the_scale_turns_logarithmic_only_where_a_linear_axis_hides_a_flagged_candidate():
    """Evidence 20 (flagged: above the line) beside 44,671 is 0.04 % of the axis on a linear
    scale: logarithmic above the line. Evidence within 100 x the line stays linear."""
    assert evidence_scale([44671.0, 20.0, 0.0], THR) == "symlog"
    assert evidence_scale([100.0 * THR, 20.0, 0.0], THR) == "linear"
    assert evidence_scale([], THR) == "linear"


def test_the_ranking_is_drawn_on_either_scale(tmp_path):
    for top in (44671.0, 40.0):
        sc = [SimpleNamespace(effect=f"e{k}", evidence=v)
              for k, v in enumerate([top, 19.5, 0.0])]
        name = plot_ranking(sc, {s.effect: 0.5 for s in sc}, tmp_path / f"r{top:g}.png")
        assert (tmp_path / name).stat().st_size > 10_000


def test_the_selected_effects_bars_are_marked(tmp_path):
    """The selected effect's bar is drawn in the 'selected' colour (matplotlib's C0,
    #1f77b4), and nothing is when none is selected: counted as pixels within 2/255 of it
    per channel (anti-aliased edges aside, a bar is thousands)."""
    import matplotlib.image as mpimg

    sc = [SimpleNamespace(effect=f"e{k}", evidence=v) for k, v in enumerate([900.0, 30.0, 0.0])]
    blue = np.array([0x1F, 0x77, 0xB4]) / 255.0

    def blue_pixels(selected):
        name = plot_ranking(sc, {"e0": 0.99}, tmp_path / f"s{len(selected)}.png",
                            {"e0": 0.98, "e1": 4.1}, selected)
        img = mpimg.imread(tmp_path / name)[..., :3]
        return int((np.abs(img - blue) < 2.0 / 255.0).all(-1).sum())

    assert blue_pixels(["e0"]) > 2000
    assert blue_pixels([]) == 0


def test_the_candidates_that_cannot_be_ruled_out_are_hatched(tmp_path):
    """A candidate the verdict cannot rule out gets its bar hatched in matplotlib's C2
    (#2ca02c): hundreds of its pixels; none where there is no caveat, nor where the caveat
    names the selected effect (its bar stays the selected colour)."""
    import matplotlib.image as mpimg

    sc = [SimpleNamespace(effect=f"e{k}", evidence=v) for k, v in enumerate([900.0, 30.0, 0.0])]
    green = np.array([0x2C, 0xA0, 0x2C]) / 255.0

    def green_pixels(caveat, selected=()):
        name = plot_ranking(sc, {}, tmp_path / f"c{len(caveat)}{len(selected)}.png", None,
                            selected, caveat)
        img = mpimg.imread(tmp_path / name)[..., :3]
        return int((np.abs(img - green) < 2.0 / 255.0).all(-1).sum())

    assert green_pixels(["e0"]) > 200
    assert green_pixels([]) == 0
    assert green_pixels(["e0"], ["e0"]) == 0
