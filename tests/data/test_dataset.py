"""Dataset format round trip, PairDataset and PairDataModule batches, mixing and subsampling."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest
import torch

from tnf.data import SPLITS, PairDataset, PairWriter, open_pairs, write_manifest
from tnf.errors import TnfError


def make_dataset(
    folder, objects=("a", "b", "c"), touches=6, frames=1, seed=0, novel=("c",), sensor="digit", **sensor_config
):
    """A small dataset of random images: per object `touches` touches of `frames` frames each.

    Training objects' touches cycle train, train, val, novel_view; novel objects' are all novel_object.
    """
    rng = np.random.default_rng(seed)
    rows = []
    for oid, name in enumerate(objects):
        for t in range(touches):
            split = "novel_object" if name in novel else ("train", "train", "val", "novel_view")[t % 4]
            rows += [(oid, t, SPLITS.index(split))] * frames
    n = len(rows)
    bg = rng.integers(0, 256, (2, 128, 128, 3), dtype=np.uint8)
    data = {
        "rgb": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
        "depth": rng.random((n, 128, 128)).astype(np.float16),
        "tactile": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
    }
    data["rgb"][:, 0, 0] = [0, 255, 128]  # known values to check the [-1, 1] mapping
    data["depth"][:, 0, 0] = [0.0]
    data["depth"][:, 0, 1] = [1.0]
    arr = np.array(rows)
    meta = {
        "background_index": (arr[:, 0] % 2).astype(np.int32),
        "object_id": arr[:, 0].astype(np.int32),
        "split": arr[:, 2].astype(np.int8),
        "touch_index": arr[:, 1].astype(np.int32),
        "sensor_id": np.zeros(n, np.int16),
    }
    with PairWriter(folder, n, bg) as w:
        for s in range(0, n, 5):  # several chunks, as the builder streams
            w.write(s, **{k: v[s : s + 5] for k, v in {**data, **meta}.items()})
    # The sensor record `tnf pair` writes (the mirror augmentation reads it).
    record = {"name": sensor, "config": {"noise_std": 0.0, **sensor_config}}
    write_manifest(folder, {"objects": list(objects), "sensors": [sensor], "sensor": record, "count": n})
    return {**data, **meta, "backgrounds": bg}


def test_round_trip(tmp_path):
    ref = make_dataset(tmp_path / "ds")
    a = open_pairs(tmp_path / "ds")
    assert len(a) == 18 and a.objects == ["a", "b", "c"]
    for k in ("rgb", "depth", "tactile", "background_index", "object_id", "split", "touch_index", "backgrounds"):
        np.testing.assert_array_equal(np.asarray(getattr(a, k)), ref[k])
    assert isinstance(a.rgb, np.memmap)
    assert a.rgb.dtype == np.uint8 and a.depth.dtype == np.float16


def test_writer_refuses_unwritten_rows(tmp_path):
    bg = np.zeros((1, 128, 128, 3), np.uint8)
    w = PairWriter(tmp_path / "ds", 3, bg)
    with pytest.raises(RuntimeError, match="never written"):
        w.close()


def test_open_refuses_non_dataset(tmp_path):
    with pytest.raises(TnfError, match="tnf pair"):
        open_pairs(tmp_path)


def test_items_values_and_splits(tmp_path):
    ref = make_dataset(tmp_path / "ds")
    ds = PairDataset(tmp_path / "ds", splits=("train",))
    assert len(ds) == 2 * 4  # objects a, b: touches 0, 1, 4, 5
    item = ds[0]
    assert item["rgb"].shape == (3, 128, 128) and item["rgb"].dtype == torch.float32
    assert item["depth"].shape == (1, 128, 128) and item["background"].shape == (3, 128, 128)
    assert item["tactile"].shape == (3, 128, 128) and item["object_id"].dtype == torch.long
    row = int(ds.index[0])
    assert item["rgb"][:, 0, 0].tolist() == [
        -1.0,
        pytest.approx(1.0, abs=2**-23),
        pytest.approx(128 / 127.5 - 1, abs=1e-6),
    ]
    assert item["depth"][0, 0, :2].tolist() == [-1.0, 1.0]
    expect_t = torch.from_numpy(ref["tactile"][row]).permute(2, 0, 1).float() / 127.5 - 1
    torch.testing.assert_close(item["tactile"], expect_t)
    expect_bg = torch.from_numpy(ref["backgrounds"][ref["background_index"][row]]).permute(2, 0, 1) / 127.5 - 1
    torch.testing.assert_close(item["background"], expect_bg.float())
    for k in ("rgb", "depth", "background", "tactile"):
        assert item[k].min() >= -1 and item[k].max() <= 1
    assert set(np.asarray(ref["object_id"])[ds.index]) == {0, 1}
    novel = PairDataset(tmp_path / "ds", splits=("novel_object",))
    assert len(novel) == 6 and {int(novel[i]["object_id"]) for i in range(6)} == {2}
    assert PairDataset(tmp_path / "ds", splits=("train", "val")).split_counts() == {"train": 8, "val": 2}


def test_conversion_of_every_value(tmp_path):
    """All 256 uint8 values and all float16 depths in [0, 1] map into [-1, 1]: 0 to -1, the top to 1 (uint8 255
    to within 2**-23 below it, never above), the rest within 1.2e-7 of x * 2/255 - 1 and exactly 2d - 1;
    whole batches, rows of a read-only memory map, and odd sizes (vector loops' tails) alike."""
    from tnf.data.dataset import _depth_to_unit_range, _to_unit_range

    values = np.arange(256, dtype=np.uint8)
    ref = values.astype(np.float64) * 2 / 255 - 1
    images = np.stack([np.roll(values, k).repeat(3 * 64).reshape(128, 128, 3) for k in range(5)])  # [5, H, W, 3]
    np.save(tmp_path / "u8.npy", images)
    mapped = np.load(tmp_path / "u8.npy", mmap_mode="r")
    odd = torch.from_numpy(np.tile(values, 7)[:-3].reshape(1, 1, -1, 1).copy())  # 1789 values: not a multiple of 16
    for out, src in [
        (_to_unit_range(images), images),
        (_to_unit_range(mapped, [3, 0, 3, 4]), images[[3, 0, 3, 4]]),
        (_to_unit_range(torch.from_numpy(images)[:1].expand(4, -1, -1, -1)), images[[0, 0, 0, 0]]),
        (_to_unit_range(odd), odd.numpy()),
    ]:
        assert out.dtype == torch.float32 and out.shape == (len(src), src.shape[3], *src.shape[1:3])
        assert out.permute(0, 2, 3, 1).is_contiguous()  # channels-last
        got = out.permute(0, 2, 3, 1).numpy().astype(np.float64)
        assert got.min() >= -1 and got.max() <= 1
        assert (got[src == 0] == -1).all() and (got[src == 255] >= 1 - 2**-23).all()
        assert np.abs(got - ref[src]).max() <= 1.2e-7
        for v in range(256):  # each value maps to one float wherever it is
            assert len(np.unique(got[src == v])) == 1

    halfs = np.arange(0, 0x3C01, dtype=np.uint16).view(np.float16)  # every float16 from 0 to 1
    assert halfs[-1] == 1 and np.all(np.diff(halfs.astype(np.float32)) > 0)
    depth = np.resize(halfs, (2, 128, 128)).copy()  # [2, H, W], every value at least once
    np.save(tmp_path / "d.npy", depth)
    for out, src in [
        (_depth_to_unit_range(depth), depth),
        (_depth_to_unit_range(np.load(tmp_path / "d.npy", mmap_mode="r"), [1, 0, 1]), depth[[1, 0, 1]]),
        (_depth_to_unit_range(halfs[None, None, :-2]), halfs[None, None, :-2]),
    ]:
        assert out.dtype == torch.float32 and out.shape == (len(src), 1, *src.shape[1:])
        np.testing.assert_array_equal(out[:, 0].numpy(), src.astype(np.float32) * 2 - 1)


def test_batch_equals_items(tmp_path):
    make_dataset(tmp_path / "ds")
    ds = PairDataset(tmp_path / "ds", splits=("train", "val", "novel_view", "novel_object"))
    idx = [5, 0, 17, 3]
    batch = ds.__getitems__(idx)
    for j, i in enumerate(idx):
        for k, v in ds[i].items():
            torch.testing.assert_close(batch[k][j], v)


def test_per_object_keeps_whole_touches(tmp_path):
    ref = make_dataset(tmp_path / "ds", touches=8, frames=3)
    ds = PairDataset(tmp_path / "ds", splits=("train",), per_object=2, seed=1)
    obj = ref["object_id"][ds.index]
    touch = ref["touch_index"][ds.index]
    for o in (0, 1):
        chosen = set(touch[obj == o])
        assert len(chosen) == 2
        assert (obj == o).sum() == 2 * 3  # every frame of each chosen touch
    again = PairDataset(tmp_path / "ds", splits=("train",), per_object=2, seed=1)
    np.testing.assert_array_equal(ds.index, again.index)
    assert len(PairDataset(tmp_path / "ds", per_object=100)) == len(PairDataset(tmp_path / "ds"))


def test_extra_touches_add_to_the_same_per_object_touches(tmp_path):
    """T-N+'s set: the touches per_object keeps, and extra_touches more from any object's others."""
    ref = make_dataset(tmp_path / "ds", touches=8, frames=3)
    base = PairDataset(tmp_path / "ds", splits=("train",), per_object=2, seed=1)
    plus = PairDataset(tmp_path / "ds", splits=("train",), per_object=2, seed=1, extra_touches=3)

    def touches(ds):
        return set(zip(ref["object_id"][ds.index].tolist(), ref["touch_index"][ds.index].tolist(), strict=True))

    assert touches(base) < touches(plus)
    assert len(touches(plus)) == len(touches(base)) + 3
    assert len(plus) == len(base) + 3 * 3  # every frame of each added touch
    # more than are left: all of them
    every = PairDataset(tmp_path / "ds", splits=("train",), per_object=2, seed=1, extra_touches=10_000)
    assert len(every) == len(PairDataset(tmp_path / "ds", splits=("train",)))


@pytest.mark.parametrize(
    ("per_object", "extra", "message"),
    [
        (None, 3, "give data.per_object too"),
        (None, -2, "extra_touches must be a whole number >= 0, got -2"),
        (2, -1, "extra_touches must be a whole number >= 0, got -1"),
        (2, 2.5, "extra_touches must be a whole number >= 0, got 2.5"),
        (2, "45", "extra_touches must be a whole number >= 0, got '45'"),
        (2, True, "extra_touches must be a whole number >= 0, got True"),
        (0, 0, "per_object must be a whole number >= 1 or null, got 0"),
        ("5", 0, "per_object must be a whole number >= 1 or null, got '5'"),
    ],
)
def test_subsample_settings_are_checked(tmp_path, per_object, extra, message):
    """Bad data.per_object / data.extra_touches: one line naming the setting, from the dataset and from the data
    module alike (the latter before it opens any dataset)."""
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "ds")
    with pytest.raises(TnfError, match=re.escape(message)):
        PairDataset(tmp_path / "ds", per_object=per_object, extra_touches=extra)
    with pytest.raises(TnfError, match=re.escape(message)):
        PairDataModule([tmp_path / "missing"], per_object=per_object, extra_touches=extra)


def _mirrored(x, order=None):
    x = x.flip(-1)
    return x if order is None else x[list(order)]


def test_mirror_augment_flips_pairs_as_the_digit_mirrors(tmp_path):
    make_dataset(tmp_path / "ds")
    idx = list(range(12))
    plain = PairDataset(tmp_path / "ds", splits=SPLITS).__getitems__(idx)
    torch.manual_seed(0)
    ds = PairDataset(tmp_path / "ds", splits=SPLITS, augment=["mirror"])
    assert ds.mirror == (1, 0, 2)  # the Digit's red and green LEDs swap under the mirror
    aug = ds.__getitems__(idx)
    flipped = 0
    for i in range(len(idx)):
        if torch.equal(aug["tactile"][i], plain["tactile"][i]):
            same = lambda k, i=i: plain[k][i]  # noqa: E731
        else:
            flipped += 1
            same = lambda k, i=i: _mirrored(plain[k][i], (1, 0, 2) if k in ("tactile", "background") else None)  # noqa: E731
        for k in ("rgb", "depth", "background", "tactile"):
            assert torch.equal(aug[k][i], same(k)), (k, i)
    assert 0 < flipped < len(idx)  # seed 0 mirrors some pairs and not others
    # The dataset's shared background is not written to.
    torch.testing.assert_close(PairDataset(tmp_path / "ds", splits=SPLITS)[0]["background"], plain["background"][0])


def test_jitter_changes_only_rgb_within_range(tmp_path):
    make_dataset(tmp_path / "ds")
    plain = PairDataset(tmp_path / "ds").__getitems__(list(range(6)))
    torch.manual_seed(0)
    aug = PairDataset(tmp_path / "ds", augment=["jitter"]).__getitems__(list(range(6)))
    assert not torch.equal(aug["rgb"], plain["rgb"]) and aug["rgb"].min() >= -1 and aug["rgb"].max() <= 1
    for k in ("depth", "background", "tactile"):
        assert torch.equal(aug[k], plain[k])


def test_augment_errors(tmp_path, caplog):
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "digit")
    make_dataset(tmp_path / "omnitact", sensor="omnitact")
    with pytest.raises(TnfError, match="unknown augmentation 'rotate'"):
        PairDataset(tmp_path / "digit", augment=["rotate"])
    with pytest.raises(TnfError, match="a list of augmentations"):
        PairDataset(tmp_path / "digit", augment=True)
    # A sensor without a mirror symmetry trains without the mirror, and says so (one config serves every sensor).
    with caplog.at_level(logging.WARNING, logger="tnf.data.dataset"):
        ds = PairDataset(tmp_path / "omnitact", augment=["mirror", "jitter"])
        dm = PairDataModule([tmp_path / "omnitact"], augment=["mirror"])
    assert ds.augment == ("jitter",) and ds.mirror is None and dm.augment == () and dm.mirror is None
    assert caplog.text.count("sensor omnitact has no mirror symmetry") == 2
    assert PairDataset(tmp_path / "digit", augment=["mirror"]).mirror == (1, 0, 2)
    # Only some of the datasets mirror: a batch cannot mix mirrored and unmirrored pairs.
    with pytest.raises(TnfError, match="mirror alike.*None: no mirror symmetry"):
        PairDataModule([tmp_path / "digit", tmp_path / "omnitact"], augment=["mirror"])
    # One light on the axis: a Digit whose mirror keeps every channel, unlike the standard one.
    axis = [{"position": [0.0, 0.01, -0.02], "color": [1.0, 1.0, 1.0], "intensity": 1.0}]
    make_dataset(tmp_path / "white", lights=axis)
    with pytest.raises(TnfError, match="mirror alike"):
        PairDataModule([tmp_path / "digit", tmp_path / "white"], augment=["mirror"])
    write_manifest(tmp_path / "digit", {"objects": ["a", "b", "c"], "sensors": ["digit"], "count": 18})
    with pytest.raises(TnfError, match="does not record its sensor's settings"):
        PairDataset(tmp_path / "digit", augment=["mirror"])


def test_compact_batches_are_mirrored_on_the_device_side(tmp_path):
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "ds")
    dm = PairDataModule([tmp_path / "ds"], batch_size=16, convert_on_device=True, augment=["mirror"])
    assert dm.mirror == (1, 0, 2)
    plain = PairDataModule([tmp_path / "ds"], batch_size=16, convert_on_device=True)
    compact = next(iter(plain.val_dataloader()))
    ref = plain.on_after_batch_transfer(compact, 0)

    class Training:
        training = True
        current_epoch = 0
        global_rank = 0

    dm.trainer = Training()  # the hook augments only while training
    aug = dm.on_after_batch_transfer(compact, 0)
    flipped = [not torch.equal(aug["depth"][i], ref["depth"][i]) for i in range(len(ref["depth"]))]
    assert any(flipped) and not all(flipped)
    for i, f in enumerate(flipped):
        expect = _mirrored(ref["tactile"][i], (1, 0, 2)) if f else ref["tactile"][i]
        assert torch.equal(aug["tactile"][i], expect)


@pytest.mark.parametrize("compact", [True, False])
def test_training_draws_depend_on_seed_epoch_and_batch_alone(tmp_path, compact):
    """What a run resumed from a checkpoint relies on: a new DataModule shuffles epoch e and augments its k-th batch
    exactly as the one that ran epochs 0 .. e did, though torch's global random state differs."""
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "ds")

    class Trainer:
        training = True
        current_epoch = 0
        global_rank = 0
        distributed_sampler_kwargs = None  # one process

    def epoch_batches(dm, epoch):
        dm.trainer = Trainer()
        dm.trainer.current_epoch = epoch
        loader = dm.train_dataloader()
        loader.sampler.set_epoch(epoch)  # as Lightning does at each epoch's start
        return [dm.on_after_batch_transfer(b, 0) for b in loader]

    kw = dict(batch_size=4, convert_on_device=compact, augment=["mirror", "jitter"], seed=3)
    first = PairDataModule([tmp_path / "ds"], **kw)
    torch.manual_seed(0)
    ran = [epoch_batches(first, e) for e in range(3)]
    resumed = PairDataModule([tmp_path / "ds"], **kw)
    torch.manual_seed(123)  # another global state, as in a new process
    again = epoch_batches(resumed, 2)
    assert len(again) == len(ran[2]) > 1
    for a, b in zip(again, ran[2]):
        for k in ("rgb", "depth", "tactile"):
            assert torch.equal(a[k], b[k]), k
    assert not torch.equal(ran[1][0]["rgb"], ran[2][0]["rgb"])  # epochs differ in order or draws


def test_datamodule_batches_and_mixing(tmp_path):
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "sim", objects=("a", "b", "c"))
    make_dataset(tmp_path / "gen", objects=("b", "d"), novel=(), seed=1)
    dm = PairDataModule([tmp_path / "sim", tmp_path / "gen"], batch_size=4, seed=0)
    assert dm.object_names == ["a", "b", "c", "d"]
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    n = sum(len(b["rgb"]) for b in batches)
    assert n == 8 + 8  # sim: a, b x 4 train touches; gen: b, d x 4
    b = batches[0]
    assert b["rgb"].shape == (4, 3, 128, 128) and b["depth"].shape == (4, 1, 128, 128)
    assert b["background"].shape == (4, 3, 128, 128) and b["tactile"].shape == (4, 3, 128, 128)
    assert b["rgb"].dtype == torch.float32 and b["object_id"].dtype == torch.long
    ids = torch.cat([b["object_id"] for b in batches])
    assert set(ids.tolist()) == {0, 1, 3}  # "b" of both datasets is id 1
    val = list(dm.val_dataloader())
    assert sum(len(b["rgb"]) for b in val) == 2 + 2
    novel_view, novel_object = dm.test_dataloader()
    assert sum(len(b["rgb"]) for b in novel_object) == 6
    assert sum(len(b["rgb"]) for b in dm.test_dataloader("novel_view")) == sum(len(b["rgb"]) for b in novel_view)
    sub = PairDataModule([tmp_path / "sim", tmp_path / "gen"], batch_size=64, per_object=1)
    assert len(next(iter(sub.train_dataloader()))["rgb"]) == 4  # 1 touch x (a, b) + (b, d)


def test_datamodule_workers(tmp_path):
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "ds")
    dm = PairDataModule([tmp_path / "ds"], batch_size=3, num_workers=1)
    got = sorted(int(i) for b in dm.train_dataloader() for i in b["object_id"])
    assert got == [0] * 4 + [1] * 4


def test_datamodule_missing_dataset(tmp_path, data_root):
    from tnf.data import PairDataModule

    with pytest.raises(TnfError, match="tnf pair"):
        PairDataModule(["nope"])


def test_compact_batches_convert_to_the_same_floats(tmp_path):
    from tnf.data import PairDataModule, to_float_batch

    make_dataset(tmp_path / "ds")
    idx = [4, 1, 7]
    plain = PairDataset(tmp_path / "ds").__getitems__(idx)
    compact = PairDataset(tmp_path / "ds", compact=True).__getitems__(idx)
    assert compact["rgb"].dtype == torch.uint8 and compact["rgb"].shape == (3, 128, 128, 3)
    assert compact["depth"].dtype == torch.float16 and compact["depth"].shape == (3, 128, 128)
    converted = to_float_batch(compact)
    for k, v in plain.items():
        assert converted[k].shape == v.shape and converted[k].dtype == v.dtype
        torch.testing.assert_close(converted[k], v)
    assert to_float_batch(plain)["rgb"] is plain["rgb"]  # float batches pass through
    dm = PairDataModule([tmp_path / "ds"], batch_size=4, convert_on_device=True)
    batch = dm.on_after_batch_transfer(next(iter(dm.val_dataloader())), 0)
    assert batch["rgb"].dtype == torch.float32 and batch["rgb"].shape == (2, 3, 128, 128)


def _rows_of_object(ds, ref, obj):
    return [j for j, row in enumerate(ds.index) if ref["object_id"][row] == obj]


def test_one_background_batches_share_it_and_mirroring_leaves_it(tmp_path):
    from tnf.data import to_float_batch

    ref = make_dataset(tmp_path / "ds")
    ds = PairDataset(tmp_path / "ds", splits=("train", "val", "novel_view"))
    idx = _rows_of_object(ds, ref, 1)  # object b: all pairs have background 1
    batch = ds.__getitems__(idx)
    expect_bg = torch.from_numpy(ref["backgrounds"][1]).permute(2, 0, 1).float() / 127.5 - 1
    for i in range(len(idx)):
        torch.testing.assert_close(batch["background"][i], expect_bg)
        for k, v in ds[idx[i]].items():
            torch.testing.assert_close(batch[k][i], v)
    compact = PairDataset(tmp_path / "ds", splits=("train", "val", "novel_view"), compact=True).__getitems__(idx)
    for k, v in to_float_batch(compact).items():
        torch.testing.assert_close(v, batch[k])
    # Mirroring flips each pair's background on its own (the shared image is not flipped for all).
    torch.manual_seed(0)
    aug = PairDataset(tmp_path / "ds", splits=("train", "val", "novel_view"), augment=["mirror"]).__getitems__(idx)
    used = set()
    for i in range(len(idx)):
        f = torch.equal(_mirrored(batch["tactile"][i], (1, 0, 2)), aug["tactile"][i])
        used.add(f)
        bg = batch["background"][0]
        assert torch.equal(_mirrored(bg, (1, 0, 2)) if f else bg, aug["background"][i])
    assert used == {True, False}  # seed 0 mirrors some pairs and not others
    torch.testing.assert_close(ds[idx[0]]["background"], expect_bg)  # the dataset's own copy is untouched


def test_worker_batches_equal_main_process_batches(tmp_path):
    from tnf.data import PairDataModule

    make_dataset(tmp_path / "sim", objects=("a", "b", "c"))
    make_dataset(tmp_path / "gen", objects=("b", "d"), novel=(), seed=1)
    for compact in (False, True):
        kw = dict(batch_size=5, convert_on_device=compact)
        main = list(PairDataModule([tmp_path / "sim", tmp_path / "gen"], **kw).val_dataloader())
        dm = PairDataModule([tmp_path / "sim", tmp_path / "gen"], num_workers=1, **kw)
        workers = list(dm.val_dataloader())
        assert len(main) == len(workers) > 0
        for a, b in zip(main, workers):
            for k in a:
                torch.testing.assert_close(a[k], b[k])
            conv = dm.on_after_batch_transfer(b, 0)
            assert conv["rgb"].dtype == torch.float32 and conv["background"].shape == conv["rgb"].shape


def test_mixed_batches_equal_the_parts_items(tmp_path):
    from tnf.data import MixedPairDataset

    make_dataset(tmp_path / "sim", objects=("a", "b", "c"))
    make_dataset(tmp_path / "gen", objects=("b", "d"), novel=(), seed=1)
    names = ["a", "b", "c", "d"]
    parts = [PairDataset(tmp_path / f, object_names=names) for f in ("sim", "gen")]
    mixed = MixedPairDataset(parts)
    idx = [len(parts[0]) + 1, 0, 3, len(parts[0])]
    batch = mixed.__getitems__(idx)
    for j, i in enumerate(idx):
        part, local = (parts[0], i) if i < len(parts[0]) else (parts[1], i - len(parts[0]))
        for k, v in part[local].items():
            torch.testing.assert_close(batch[k][j], v)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="pinned memory needs a GPU")
def test_pinned_batches_with_a_shared_background(tmp_path):
    from torch.utils.data import DataLoader

    from tnf.data import collate_pairs

    ref = make_dataset(tmp_path / "ds")
    for compact in (False, True):
        ds = PairDataset(tmp_path / "ds", splits=("train", "val", "novel_view"), compact=compact)
        idx = _rows_of_object(ds, ref, 1)  # one background for the whole batch
        loader = DataLoader(ds, batch_size=len(idx), sampler=idx, pin_memory=True, collate_fn=collate_pairs)
        batch = next(iter(loader))
        plain = ds.__getitems__(idx)
        for k, v in batch.items():
            assert v.is_pinned(), k
            assert torch.equal(v, plain[k])
            assert torch.equal(v.to("cuda", non_blocking=True).cpu(), plain[k])


@pytest.mark.parametrize("convert", [True, False])
def test_every_data_setting_reaches_the_training_datamodule(convert, tmp_path):
    """``tnf train``'s PairDataModule takes each key of the data section (convert_on_device was once dropped)."""
    from tnf.stages.train import datamodule_from_cfg
    from tnf.testing import compose

    make_dataset(tmp_path / "pairs" / "some_pairs")
    cfg = compose(
        "train",
        [f"data.convert_on_device={convert}", "data.batch_size=7", "data.num_workers=1", f"data_root={tmp_path}"],
    )
    dm = datamodule_from_cfg(cfg, ["some_pairs"])
    assert dm.convert_on_device is convert
    assert (dm.batch_size, dm.num_workers) == (7, 1)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["rgb"].dtype == (torch.uint8 if convert else torch.float32)


def test_shift_moves_the_contact_and_keeps_the_background():
    """The shift moves RGB-D and the press's change from the background by whole pixels at each image's size,
    repeats the edges, and leaves the background where it is."""
    from tnf.data.augment import augment_batch, shift_batch

    g = torch.Generator().manual_seed(0)
    bg = torch.rand(1, 3, 12, 16, generator=g).expand(2, -1, -1, -1)
    tactile = bg.clone()
    tactile[:, :, 5:7, 7:9] += 0.5  # a contact at the centre
    depth = torch.ones(2, 1, 24, 32)
    depth[:, :, 10:14, 14:18] = 0.2  # the indenter, at twice the tactile's size
    batch = {"rgb": torch.rand(2, 3, 24, 32, generator=g), "depth": depth, "background": bg, "tactile": tactile}
    frac = torch.tensor([[0.5, 0.0], [-0.75, 1 / 3]])  # 4 px right; 6 px left and 2 down (at 16 x 12)
    out = shift_batch(batch, frac)
    assert "background" not in out
    torch.testing.assert_close(out["tactile"][0] - bg[0], (tactile[0] - bg[0]).roll(4, -1))
    assert torch.equal(out["depth"][0], depth[0].roll(8, -1))
    moved = (out["tactile"][1] - bg[1]).abs().sum(0) > 0.25
    assert moved.nonzero().tolist() == [[r, c] for r in (7, 8) for c in (1, 2)]
    pressed = (out["depth"][1, 0] < 1).nonzero()  # 12 px left and 4 down at 32 x 24
    assert pressed[:, 0].unique().tolist() == [14, 15, 16, 17] and pressed[:, 1].unique().tolist() == [2, 3, 4, 5]
    # The columns that moved in from the border repeat the edge column.
    assert torch.equal(out["rgb"][0, :, :, :9], batch["rgb"][0, :, :, :1].expand(-1, -1, 9))
    # Through augment_batch: about half the pairs move, the background is never written.
    many = {k: v.repeat(8, 1, 1, 1) for k, v in batch.items()}
    bg_before = many["background"].clone()
    augment_batch(many, ["shift"], generator=torch.Generator().manual_seed(1))
    same = [torch.equal(many["tactile"][i], tactile[i % 2]) for i in range(16)]
    assert 0 < sum(same) < 16
    assert torch.equal(many["background"], bg_before)
