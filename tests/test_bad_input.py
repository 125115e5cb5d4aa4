"""Bad input: one line naming the file and what is wrong, a non-zero exit, no traceback,
and nothing the user had is lost."""

import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib3r_graph.cli import main
from calib3r_graph.errors import InputError
from calib3r_graph.io.dataset import load_dataset
from calib3r_graph.io.predictions import load_predictions
from tests.conftest import SAMPLE


def run_cli(args, capsys):
    code = main(args)
    err = capsys.readouterr().err
    error_lines = [l for l in err.splitlines() if l.startswith("calib3r-graph:")]
    return code, err, error_lines


def expect_error(args, capsys, code, *fragments):
    got, err, lines = run_cli(args, capsys)
    assert got == code, err
    assert "Traceback" not in err
    assert len(lines) == 1, err
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


def edit(path, old, new):
    path.write_text(path.read_text().replace(old, new, 1))


def csv_rows(root):
    return (root / "robot_poses.csv").read_text().splitlines()


def set_row(root, i, row):
    rows = csv_rows(root)
    rows[i] = row
    (root / "robot_poses.csv").write_text("\n".join(rows) + "\n")


def test_nonexistent_dataset(capsys, tmp_path):
    expect_error(["solve", str(tmp_path / "nope"), "--out", str(tmp_path / "o")], capsys, 3, "nope", "no such")


@pytest.mark.parametrize("mutate,fragments", [
    (lambda r: (r / "dataset.yaml").unlink(), ["dataset.yaml", "missing"]),
    (lambda r: (r / "dataset.yaml").write_text("format: [unclosed\n"), ["dataset.yaml", "not valid YAML"]),
    (lambda r: edit(r / "dataset.yaml", "calib3r-dataset/1", "calib3r-dataset/9"), ["dataset.yaml", "unknown format"]),
    (lambda r: edit(r / "dataset.yaml", "cameras:", "kameras:"), ["dataset.yaml", "missing key 'cameras'"]),
    (lambda r: edit(r / "dataset.yaml", "model: PINHOLE", "model: FISHEYE"), ["dataset.yaml", "cameras[0]", "FISHEYE"]),
    (lambda r: edit(r / "dataset.yaml", "unit: m", "unit: inch"), ["robot.unit", "inch"]),
])
def test_bad_dataset_yaml(sample_copy, tmp_path, capsys, mutate, fragments):
    mutate(sample_copy)
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, *fragments)


@pytest.mark.parametrize("row,fragments", [
    ("0001,nan,0,0,0,0,0,1", ["robot_poses.csv", "row 3", "NaN"]),
    ("0001,0.1,0,0,0,0,0,0", ["robot_poses.csv", "row 3", "not unit"]),
    ("0001,0.1,0,0,0,0,0,0.5", ["robot_poses.csv", "row 3", "not unit"]),
    ("0000,0.1,0,0,0,0,0,1", ["robot_poses.csv", "row 3", "duplicated"]),
    ("0001,0.1,0,0", ["robot_poses.csv", "row 3", "columns"]),
    ("0001,a,b,c,0,0,0,1", ["robot_poses.csv", "row 3", "numbers"]),
])
def test_bad_robot_poses(sample_copy, tmp_path, capsys, row, fragments):
    set_row(sample_copy, 2, row)
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, *fragments)


def test_missing_robot_row_names_the_frame_and_skip_missing_drops_it(sample_copy, tmp_path, capsys, caplog):
    rows = csv_rows(sample_copy)
    (sample_copy / "robot_poses.csv").write_text("\n".join(r for r in rows if not r.startswith("0003,")) + "\n")
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "0003", "--skip-missing")
    code, err, _ = run_cli(["solve", str(sample_copy), "--out", str(tmp_path / "o"), "--skip-missing", "--no-cloud"],
                           capsys)
    assert code == 0, err
    assert "frame 0003 has no robot pose; skipped" in caplog.text
    traj = (tmp_path / "o" / "trajectory.csv").read_text()
    assert ",0003," not in traj and ",0004," in traj


def test_millimetres_declared_as_metres(sample_copy, tmp_path, capsys):
    rows = csv_rows(sample_copy)
    out = [rows[0]]
    for r in rows[1:]:
        f, *v = r.split(",")
        out.append(",".join([f] + [str(float(x) * 1000) for x in v[:3]] + v[3:]))
    (sample_copy / "robot_poses.csv").write_text("\n".join(out) + "\n")
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "millimetres", "unit: mm")


def test_inverted_pose_direction(sample_copy, tmp_path, capsys):
    from calib3r_graph.io.dataset import read_robot_poses, write_robot_poses

    poses = read_robot_poses(sample_copy / "robot_poses.csv")
    write_robot_poses(sample_copy / "robot_poses.csv", {f: p.inverse() for f, p in poses.items()})
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "robot_poses.csv", "inverted")


def _views_dir(root):
    return root / "predictions" / "sim" / "views"


def test_truncated_npz(sample_copy, tmp_path, capsys):
    f = _views_dir(sample_copy) / "cam0" / "0002.npz"
    f.write_bytes(f.read_bytes()[:500])
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "0002.npz", "unreadable")


def test_mismatched_shapes(sample_copy, tmp_path, capsys):
    f = _views_dir(sample_copy) / "cam1" / "0001.npz"
    d = dict(np.load(f))
    d["conf"] = d["conf"][:-3]
    np.savez(f, **d)
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "0001.npz", "conf shape")


def test_prediction_for_unknown_camera(sample_copy, tmp_path, capsys):
    shutil.copytree(_views_dir(sample_copy) / "cam1", _views_dir(sample_copy) / "cam7")
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "cam7", "unknown camera")


def _rewrite_pairs(root, **changes):
    f = root / "predictions" / "sim" / "pairs.npz"
    d = dict(np.load(f))
    d.update(changes)
    np.savez(f, **d)
    return d


def test_pairs_referencing_unknown_view(sample_copy, tmp_path, capsys):
    d = dict(np.load(sample_copy / "predictions" / "sim" / "pairs.npz"))
    va = d["view_a"].astype("<U16")
    va[0] = "cam0/9999"
    _rewrite_pairs(sample_copy, view_a=va)
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "pairs.npz", "cam0/9999")


def test_empty_pairs(sample_copy, tmp_path, capsys):
    _rewrite_pairs(sample_copy, view_a=np.array([], "<U9"), view_b=np.array([], "<U9"), offsets=np.array([0]),
                   uv_a=np.zeros((0, 2), np.float32), uv_b=np.zeros((0, 2), np.float32),
                   conf=np.zeros(0, np.float32))
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 3, "pairs.npz", "no matches")


def test_too_few_poses(sample_copy, tmp_path, capsys):
    for f in _views_dir(sample_copy).rglob("*.npz"):
        if f.stem not in ("0000", "0001"):
            f.unlink()
    d = dict(np.load(sample_copy / "predictions" / "sim" / "pairs.npz"))
    keep = [e for e in range(len(d["view_a"])) if all(v.split("/")[1] in ("0000", "0001")
                                                      for v in (d["view_a"][e], d["view_b"][e]))]
    sl = [np.arange(d["offsets"][e], d["offsets"][e + 1]) for e in keep]
    idx = np.concatenate(sl)
    _rewrite_pairs(sample_copy, view_a=d["view_a"][keep], view_b=d["view_b"][keep],
                   offsets=np.concatenate([[0], np.cumsum([len(s) for s in sl])]),
                   uv_a=d["uv_a"][idx], uv_b=d["uv_b"][idx], conf=d["conf"][idx])
    expect_error(["solve", str(sample_copy), "--out", str(tmp_path / "o")], capsys, 4, "at least 3")


def test_failed_run_keeps_previous_results(sample_copy, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["solve", str(sample_copy), "--out", str(out), "--no-cloud"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    set_row(sample_copy, 2, "0001,nan,0,0,0,0,0,1")
    expect_error(["solve", str(sample_copy), "--out", str(out)], capsys, 3, "NaN")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no staging leftovers"


def test_disconnected_covisibility_graph_is_solved_per_component(simulated, tmp_path):
    """Cut every edge between the first and second half of the frames: both halves still
    constrain the same ee_T_cam, each with its own placement."""
    from calib3r_graph.evaluation.evaluate import hand_eye_errors
    from calib3r_graph.io.dataset import load_ground_truth
    from calib3r_graph.solver.solve import SolveOptions, solve

    root = tmp_path / "d"
    shutil.copytree(simulated(seed=3, frames=14), root)
    d = dict(np.load(root / "predictions" / "sim" / "pairs.npz"))
    half = lambda v: int(str(v).split("/")[1]) < 7
    keep = [e for e in range(len(d["view_a"])) if half(d["view_a"][e]) == half(d["view_b"][e])]
    assert len(keep) < len(d["view_a"])
    sl = [np.arange(d["offsets"][e], d["offsets"][e + 1]) for e in keep]
    idx = np.concatenate(sl)
    _rewrite_pairs(root, view_a=d["view_a"][keep], view_b=d["view_b"][keep],
                   offsets=np.concatenate([[0], np.cumsum([len(s) for s in sl])]),
                   uv_a=d["uv_a"][idx], uv_b=d["uv_b"][idx], conf=d["conf"][idx])
    ds = load_dataset(root)
    preds = load_predictions(root, "sim", ds.cameras, set(ds.frames))
    sol = solve(ds, preds, SolveOptions())
    e = hand_eye_errors(sol.ee_T_cam, load_ground_truth(root))["cam0"]
    assert e["e_t_m"] < 3e-3 and np.degrees(e["e_theta_rad"]) < 0.2


# --- fuzzing: random corruptions of a valid dataset never raise anything but InputError ---

FUZZ_TARGETS = ["dataset.yaml", "robot_poses.csv", "predictions/sim/pairs.npz", "predictions/sim/views/cam0/0001.npz"]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(target=st.sampled_from(FUZZ_TARGETS), pos=st.floats(0, 1), data=st.binary(min_size=0, max_size=12),
       mode=st.sampled_from(["overwrite", "truncate", "insert"]))
def test_fuzz_loaders_raise_only_input_errors(tmp_path_factory, target, pos, data, mode):
    root = tmp_path_factory.mktemp("fuzz") / "d"
    shutil.copytree(SAMPLE, root, ignore=shutil.ignore_patterns("images", "depth"))
    f = root / target
    raw = bytearray(f.read_bytes())
    i = int(pos * len(raw))
    if mode == "overwrite":
        raw[i:i + len(data)] = data
    elif mode == "truncate":
        raw = raw[:i]
    else:
        raw[i:i] = data
    f.write_bytes(bytes(raw))
    try:
        ds = load_dataset(root)
        load_predictions(root, "sim", ds.cameras, set(ds.frames))
    except InputError as e:
        assert "\n" not in str(e) and str(root) in str(e)
