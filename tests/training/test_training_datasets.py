"""weathergen.training.datasets: readers as PyTorch datasets, collation, worker processes."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader

from conftest import write_fake_sintel
from fake_datasets import demo_sequence, write_fake_custom, write_fake_kitti, write_fake_spring
from weathergen.datasets import open_dataset
from weathergen.errors import ShapeError
from weathergen.framepair import _TENSOR_FIELDS
from weathergen.training import EpochSampler, PairDataset, collate_pairs, pair_of

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def assert_same_pair(a, b):
    assert a.id == b.id
    for name in _TENSOR_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and torch.equal(x, y), name


@pytest.fixture(scope="module")
def readers(tmp_path_factory, demo_root):
    """One opened reader of every kind: demo, and tiny Sintel, KITTI, Spring and custom trees."""
    tmp = tmp_path_factory.mktemp("readers")
    frames, pairs = demo_sequence("street")
    write_fake_kitti(tmp / "kitti", pairs[0])
    write_fake_spring(tmp / "spring", frames[:3], pairs=pairs[:2])
    write_fake_custom(tmp / "custom", frames[:3])
    return {
        "demo": open_dataset("demo"),
        "sintel": open_dataset("sintel", write_fake_sintel(tmp / "sintel")),
        "kitti": open_dataset("kitti", tmp / "kitti"),
        "spring": open_dataset("spring", tmp / "spring", split="train"),
        "custom": open_dataset("custom", tmp / "custom"),
    }


@pytest.mark.parametrize("name", ["demo", "sintel", "kitti", "spring", "custom"])
def test_dataset_yields_what_the_reader_loads(readers, name):
    reader = readers[name]
    data = PairDataset(reader)
    refs = reader.pairs()
    assert len(data) == len(refs) > 0
    for i, ref in enumerate(refs):
        sample = data[i]
        assert sample.index == i and sample.epoch == 0
        assert sample.world_up == reader.world_up
        assert_same_pair(sample.pair, reader.load(ref))
    assert_same_pair(data[-1].pair, reader.load(refs[-1]))
    with pytest.raises(IndexError):
        data[len(refs)]


def test_flow_and_validity_come_through_where_the_dataset_has_them(readers):
    kitti = PairDataset(readers["kitti"])[0].pair
    assert kitti.flow is not None and kitti.flow_valid is not None and not bool(kitti.flow_valid.all())
    assert PairDataset(readers["sintel"])[0].pair.flow is not None


def test_collate_stacks_pairs_and_keys(readers):
    data = PairDataset(readers["demo"])
    samples = [data[i] for i in (4, 1, 2)]
    batch = collate_pairs(samples)
    assert len(batch) == 3
    assert batch.indices.tolist() == [4, 1, 2] and batch.epochs.tolist() == [0, 0, 0]
    assert batch.pairs.image1.shape == (3, 3, 176, 384)
    assert batch.pairs.flow.shape == (3, 2, 176, 384)
    for k, s in enumerate(samples):
        assert_same_pair(pair_of(batch.pairs, k), s.pair)
        assert batch.sample(k).index == s.index


def test_collate_refuses_pairs_of_different_sizes(readers):
    demo = PairDataset(readers["demo"])[0]
    sintel = PairDataset(readers["sintel"])[0]
    with pytest.raises(ShapeError, match="different sizes"):
        collate_pairs([demo, sintel])


def test_dataloader_with_two_workers_gives_the_readers_tensors(readers):
    reader = readers["demo"]
    data = PairDataset(reader)
    loader = DataLoader(data, batch_size=3, num_workers=2, collate_fn=collate_pairs)
    batches = list(loader)
    assert [b.indices.tolist() for b in batches] == [[0, 1, 2], [3, 4, 5]]
    refs = reader.pairs()
    for b in batches:
        for k, i in enumerate(b.indices.tolist()):
            assert_same_pair(pair_of(b.pairs, k), reader.load(refs[i]))


def test_epoch_reaches_items_by_set_epoch_and_by_epoch_keys(readers):
    data = PairDataset(readers["demo"])
    data.set_epoch(3)
    assert data[2].epoch == 3
    assert data[(7, 2)].epoch == 7 and data[(7, 2)].index == 2
    sampler = EpochSampler(range(3))
    sampler.set_epoch(5)
    assert list(sampler) == [(5, 0), (5, 1), (5, 2)] and len(sampler) == 3


def test_epoch_sampler_carries_the_epoch_to_persistent_workers(readers):
    data = PairDataset(readers["demo"])
    sampler = EpochSampler(range(len(data)))
    loader = DataLoader(data, sampler=sampler, batch_size=3, num_workers=2,
                        persistent_workers=True, collate_fn=collate_pairs)
    seen = []
    for epoch in (0, 1):
        sampler.set_epoch(epoch)
        seen.append(sorted({e for b in loader for e in b.epochs.tolist()}))
    assert seen == [[0], [1]]
