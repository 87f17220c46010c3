"""Generated bad inputs for tnf's loaders: every failure is a TnfError, never another exception or a hang."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from tests.reliability.helpers import cube_obj
from tnf.errors import TnfError

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# JSON values of every kind, nested a little.
json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=20,
)


def ok_or_tnf_error(fn, *args):
    """Run ``fn``; a raised exception must be a one-line TnfError."""
    try:
        return fn(*args)
    except TnfError as e:
        assert str(e) and "\n" not in str(e).strip()
        return None


# -- transforms.json ---------------------------------------------------------------------------------------
def _good_capture(folder: Path, n: int = 2, size: int = 8) -> dict:
    (folder / "images").mkdir(parents=True)
    (folder / "depth").mkdir()
    frames = []
    for i in range(n):
        Image.new("RGBA", (size, size), (i, 2, 3, 255)).save(folder / f"images/train_{i:03d}.png")
        np.save(folder / f"depth/train_{i:03d}.npy", np.ones((size, size), np.float32))
        m = np.eye(4)
        m[2, 3] = 1.0
        frames.append(
            {
                "file_path": f"images/train_{i:03d}.png",
                "depth_file_path": f"depth/train_{i:03d}.npy",
                "transform_matrix": m.tolist(),
            }
        )
    return {"fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 4.0, "w": size, "h": size, "frames": frames}


FRAME_KEYS = ("file_path", "depth_file_path", "transform_matrix")
TOP_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "frames")


@st.composite
def mutated_transforms(draw):
    """A valid transforms dict with a few keys replaced by arbitrary JSON values or deleted."""
    ops = draw(
        st.lists(
            st.tuples(
                st.sampled_from(TOP_KEYS + tuple(f"frame.{k}" for k in FRAME_KEYS) + ("matrix.row", "matrix.cell")),
                st.one_of(st.just("<delete>"), json_values),
            ),
            min_size=1,
            max_size=3,
        )
    )
    return ops


def _apply(meta: dict, ops) -> dict:
    for key, value in ops:
        if key.startswith("frame."):
            target, k = meta["frames"][0] if isinstance(meta.get("frames"), list) and meta["frames"] else {}, key[6:]
        elif key.startswith("matrix."):
            fr = meta["frames"][0] if isinstance(meta.get("frames"), list) and meta["frames"] else None
            m = fr.get("transform_matrix") if isinstance(fr, dict) else None
            if not isinstance(m, list) or not m or not isinstance(m[0], list) or not m[0]:
                continue
            target, k = (m, 1) if key == "matrix.row" else (m[0], 0)
            if value == "<delete>":
                target.pop(k if k < len(target) else 0)
            else:
                target[k % len(target)] = value
            continue
        else:
            target, k = meta, key
        if not isinstance(target, dict):
            continue
        if value == "<delete>":
            target.pop(k, None)
        else:
            target[k] = value
    return meta


@FUZZ
@given(ops=mutated_transforms())
def test_load_transforms_with_mutated_fields(ops):
    from tnf.cameras import load_transforms

    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        meta = _apply(_good_capture(folder), ops)
        (folder / "transforms.json").write_text(json.dumps(meta))
        out = ok_or_tnf_error(load_transforms, folder)
        if out is not None:
            images, c2w, intr, w, h, depth = out
            assert images.shape[1:] == (h, w, 4) and c2w.shape[1:] == (4, 4) and np.isfinite(c2w).all()


def test_a_missing_image_whose_name_holds_a_newline_is_still_a_one_line_error():
    # A case the fuzzing above found: the path was printed as it is, newline and all.
    from tnf.cameras import load_transforms

    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        meta = _apply(_good_capture(folder), [("frame.file_path", "\n")])
        (folder / "transforms.json").write_text(json.dumps(meta))
        with pytest.raises(TnfError, match=r"frame 0 image not found: '.*\\n\.png'$") as e:
            load_transforms(folder)
        assert "\n" not in str(e.value)


@FUZZ
@given(top=json_values)
def test_load_transforms_with_any_json(top):
    from tnf.cameras import load_transforms

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "transforms.json").write_text(json.dumps(top))
        assert ok_or_tnf_error(load_transforms, d) is None  # nothing arbitrary is a valid capture


@FUZZ
@given(data=st.binary(max_size=200), which=st.sampled_from(["transforms.json", "image", "depth"]))
def test_load_transforms_with_bad_bytes(data, which):
    from tnf.cameras import load_transforms

    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        meta = _good_capture(folder)
        (folder / "transforms.json").write_text(json.dumps(meta))
        target = {
            "transforms.json": "transforms.json",
            "image": meta["frames"][1]["file_path"],
            "depth": meta["frames"][1]["depth_file_path"],
        }[which]
        (folder / target).write_bytes(data)
        ok_or_tnf_error(load_transforms, folder)


# -- touch and dataset manifests ---------------------------------------------------------------------------
TOUCH_KEYS = ("index", "split", "image", "start_c2w", "contact_point")


@FUZZ
@given(
    top=st.one_of(json_values, st.just(None)),
    touch_ops=st.lists(st.tuples(st.sampled_from(TOUCH_KEYS), st.one_of(st.just("<delete>"), json_values)), max_size=3),
)
def test_touch_manifest_reader(top, touch_ops):
    from tnf.data.render import TouchItem

    good = {
        "index": 0,
        "split": "train",
        "image": "images/00000.png",
        "start_c2w": np.eye(4).tolist(),
        "contact_point": [0.0, 0.0, 0.0],
    }
    for k, v in touch_ops:
        if v == "<delete>":
            good.pop(k, None)
        else:
            good[k] = v
    manifest = {"touches": [good]} if top is None else top
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "manifest.json").write_text(json.dumps(manifest))
        item = ok_or_tnf_error(TouchItem.load, d)
        if item is not None:  # a manifest that loads gives poses and distances without errors
            assert item.start_poses().shape == (len(item.touches), 4, 4)
            assert item.contact_distances().shape == (len(item.touches),)


@pytest.fixture(scope="module")
def dataset_template(tmp_path_factory):
    from tests.generators.test_stages import write_pairs

    folder = tmp_path_factory.mktemp("ds") / "pairs"
    write_pairs(folder, n=3)
    return folder


MANIFEST_KEYS = ("format_version", "objects", "count", "splits", "sensors")
ARRAY_NAMES = ("rgb", "depth", "tactile", "background_index", "object_id", "split", "touch_index", "backgrounds")


@FUZZ
@given(
    manifest_ops=st.lists(
        st.tuples(st.sampled_from(MANIFEST_KEYS), st.one_of(st.just("<delete>"), json_values)), max_size=2
    ),
    array=st.one_of(
        st.none(),
        st.tuples(
            st.sampled_from(ARRAY_NAMES),
            st.sampled_from(["uint8", "int8", "int32", "float16", "float64"]),
            st.lists(st.integers(0, 4), max_size=4),
            st.integers(-3, 9),
        ),
        st.tuples(st.sampled_from(ARRAY_NAMES), st.binary(max_size=100)),
    ),
)
def test_dataset_reader(dataset_template, manifest_ops, array):
    from tnf.data import PairDataset, open_pairs

    with tempfile.TemporaryDirectory() as d:
        folder = Path(d) / "ds"
        shutil.copytree(dataset_template, folder)
        m = json.loads((folder / "manifest.json").read_text())
        for k, v in manifest_ops:
            if v == "<delete>":
                m.pop(k, None)
            else:
                m[k] = v
        (folder / "manifest.json").write_text(json.dumps(m))
        if array is not None and len(array) == 4:
            name, dtype, shape, fill = array
            np.save(folder / f"{name}.npy", np.full(shape, fill).astype(dtype))
        elif array is not None:
            (folder / f"{array[0]}.npy").write_bytes(array[1])
        if ok_or_tnf_error(open_pairs, folder) is not None:  # an accepted dataset serves whole batches
            ds = ok_or_tnf_error(PairDataset, folder, ("train", "val", "novel_view", "novel_object"))
            if ds is not None and len(ds):
                batch = ds.__getitems__(list(range(len(ds))))
                assert batch["rgb"].shape[1:] == (3, 128, 128)


# -- meshes ------------------------------------------------------------------------------------------------
def _mesh_text_mutation():
    lines = cube_obj().splitlines()
    junk = st.one_of(
        st.sampled_from(["nan", "inf", "-inf", "1e400", "0", "-1", "99", "x", "", "1/2/3", "0.0.0"]),
        st.floats(allow_nan=True).map(repr),
        st.integers(-50, 50).map(str),
    )
    return st.lists(st.tuples(st.integers(0, len(lines) - 1), st.integers(1, 3), junk), min_size=1, max_size=4).map(
        lambda edits: _edit(lines, edits)
    )


def _edit(lines, edits) -> bytes:
    out = [ln.split() for ln in lines]
    for row, col, tok in edits:
        parts = out[row]
        if col < len(parts):
            parts[col] = tok
    return ("\n".join(" ".join(p) for p in out) + "\n").encode()


@FUZZ
@given(
    content=st.one_of(
        st.binary(max_size=300),
        _mesh_text_mutation(),
        st.binary(min_size=84, max_size=200).map(lambda b: b[:80] + (3).to_bytes(4, "little") + b[84:]),  # binary STL
        st.binary(max_size=120).map(lambda b: b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n" + b),
    ),
    suffix=st.sampled_from([".obj", ".ply", ".stl", ".off"]),
)
def test_mesh_dir_with_bad_files(content, suffix):
    from tnf.registry import OBJECTS

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / f"bad{suffix}").write_bytes(content)
        src = ok_or_tnf_error(OBJECTS.build, {"name": "mesh_dir", "path": d, "skip_invalid": False})
        if src is None:
            return
        for name in src.names():
            mesh = ok_or_tnf_error(src.load, name)
            if mesh is not None:  # a mesh that passes validation is a usable solid
                assert len(mesh.faces) and np.isfinite(mesh.vertices).all()
