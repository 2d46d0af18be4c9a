"""Padding as each benchmark's evaluation does it: Sintel evenly top and bottom, KITTI at the bottom."""

from __future__ import annotations

import pytest
import torch

from weathergen.datasets import DATASETS
from weathergen.models import InputPadder
from weathergen.models.base import FlowModel


def test_kitti_rows_go_to_the_bottom_and_sintel_rows_are_split():
    # KITTI 2015 frames are 375 x 1242: 1 row and 6 columns to a multiple of 8
    kitti = InputPadder(375, 1242, placement="bottom")
    assert (kitti.top, kitti.bottom, kitti.left, kitti.right) == (0, 1, 3, 3)
    sintel = InputPadder(436, 1024)                      # 4 rows: 2 above, 2 below
    assert (sintel.top, sintel.bottom, sintel.left, sintel.right) == (2, 2, 0, 0)
    odd = InputPadder(13, 10, placement="bottom")        # 3 rows, 6 columns
    assert (odd.top, odd.bottom, odd.left, odd.right) == (0, 3, 3, 3)
    x = torch.arange(13 * 10, dtype=torch.float32).reshape(1, 1, 13, 10)
    padded = odd.pad(x)
    assert padded.shape[-2:] == (16, 16)
    assert torch.equal(padded[..., :13, 3:13], x)               # the frame sits at the top
    assert torch.equal(padded[..., 13:, 3:13], x[..., 12:13, :].expand(1, 1, 3, 10))   # replicated
    assert torch.equal(odd.unpad(padded), x)
    with pytest.raises(ValueError, match="placement must be one of even, bottom, got 'top'"):
        InputPadder(10, 10, placement="top")


def test_datasets_name_their_protocol_and_models_follow_it():
    assert DATASETS["kitti"].padding == "bottom"
    assert {DATASETS[n].padding for n in ("sintel", "demo", "spring", "custom")} == {"even"}

    class Echo(FlowModel):
        multiple = 8

        def normalize(self, image):
            return image

        def predict(self, image1, image2):
            self.seen = image1.shape[-2:]
            return image1[:, :2]         # "flow" = the padded frame's first two channels

    net = Echo()
    image = torch.rand(1, 3, 13, 10)
    even = net(image, image)
    net.padding = "bottom"
    bottom = net(image, image)
    # both crop back exactly to the frame, wherever the padding went
    assert torch.equal(even, image[:, :2]) and torch.equal(bottom, image[:, :2])
    assert net.padder(13, 10).top == 0 and Echo().padder(13, 10).top == 1
