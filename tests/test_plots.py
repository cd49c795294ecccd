"""Pictures: written where asked, in the format asked."""

import numpy as np
import pytest

from taichi_match import io, plots
from taichi_match.merge import merge_maps
from taichi_match.scenes import corridor


def test_save_merge_draws_a_b_and_the_merge(tmp_path):
    a = corridor()
    merged = merge_maps(a, a, (0.5, 0.0, 0.1))
    path = tmp_path / "merged.png"
    plots.save_merge(path, a, a, merged, title="corridor")
    image = np.asarray(io.read_image(str(path)))
    assert image.shape[:2] == (468, 1350)            # three panels: 15 x 5.2 inches at 90 dpi
    assert len(np.unique(image.reshape(-1, image.shape[-1]) if image.ndim == 3 else image, axis=0)) > 3


def test_save_overlay_refuses_an_unknown_format(tmp_path):
    a = corridor()
    with pytest.raises(Exception, match="png"):
        plots.save_overlay(tmp_path / "o.jpg", a, a, (0, 0, 0), None)
