"""``egoposevr motion inspect`` and ``synth`` over a motion library of rigs the test writes itself."""

import json

import numpy as np
from rigfamilies import FAMILY, Layout, reference_motion, write_family_bvh

from egoposevr.cli.main import main


def _library(root):
    rot, trans = reference_motion(frames=150, fps=60.0)
    for family, subject, layout in (
        ("mixamo", "alice", Layout()),
        ("3ds-max-biped", "bob", Layout(z_up=True, units_per_m=100.0, a_pose_deg=30)),
        ("unknown-names", "carol", Layout(units_per_m=1 / 0.0254)),
        ("perception-neuron", "dave", Layout(six_channels=True)),
    ):
        (root / subject).mkdir(parents=True)
        (root / subject / f"{family}.bvh").write_text(
            write_family_bvh(FAMILY[family], layout, rot, trans, 60.0)
        )
    (root / "carol" / "copy.bvh").write_bytes((root / "alice" / "mixamo.bvh").read_bytes())
    poses = np.zeros((120, 156))
    poses[:, 50] = np.linspace(0, 1, 120)  # the left knee bends
    np.savez(root / "dave" / "amass.npz", poses=poses, trans=np.zeros((120, 3)), mocap_framerate=60.0)
    (root / "bob" / "armless.bvh").write_text(
        "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 1 Xrotation } MOTION"
    )
    return root


def test_inspect_reports_rigs_errors_splits_and_pictures(tmp_path, capsys):
    lib = _library(tmp_path / "lib")
    code = main(["motion", "inspect", str(lib), "--png", str(tmp_path / "png"), "--json", str(tmp_path / "r.json"),
                 "--split-by-subject", "train=0.6,val=0.4"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 1  # one file could not be used
    assert "armless.bvh: cannot use" in out and "duplicate:" in out
    report = json.loads((tmp_path / "r.json").read_text())
    by_family = {f["family"]: f for f in report["files"]}
    assert set(by_family) == {"mixamo", "3ds-max-biped", "unrecognised", "perception-neuron", "amass"}
    assert by_family["3ds-max-biped"]["units"] == "cm" and by_family["3ds-max-biped"]["up_axis"] == "+Z"
    assert by_family["unrecognised"]["units"] == "inch"
    assert all(f["retarget_error_cm"]["p95"] < 3.0 for f in report["files"])
    assert by_family["amass"]["duration_s"] == 2.0
    # one motion through four rigs: its feet move alike whichever rig carried it, and as in the files
    slides = [f["feet"]["slide"] for f in report["files"] if f["family"] != "amass"]
    assert len(slides) == 4 and max(slides) - min(slides) < 0.02
    assert all(
        abs(f["feet"]["source_slide"] - f["feet"]["slide"]) < 0.2
        for f in report["files"]
        if f["family"] != "amass"
    )
    splits = report["summary"]["splits"]
    assert sorted(splits["train"]["subjects"] + splits["val"]["subjects"]) == [
        "alice",
        "bob",
        "carol",
        "dave",
    ]
    assert len(list((tmp_path / "png").glob("*.png"))) == 4


def test_inspect_one_file_prints_its_mapping(tmp_path, capsys):
    lib = _library(tmp_path / "lib")
    assert (
        main(["motion", "inspect", str(lib / "alice" / "mixamo.bvh"), "--png", str(tmp_path / "a.png")]) == 0
    )
    out = capsys.readouterr().out
    assert "left_elbow      <- mixamorig:LeftForeArm" in out
    assert (tmp_path / "a.png").stat().st_size > 5000


def test_synth_takes_a_library_split_by_subject(tmp_path, capsys):
    lib = _library(tmp_path / "lib")
    args = ["synth", "--motion", str(lib), "--split-by-subject", "train=0.6,val=0.4", "--seconds", "2",
            "--resolution", "64x48", "--no-progress", "--out", str(tmp_path / "ds")]  # fmt: skip
    assert main([*args, "--split", "train"]) == 0
    assert main([*args, "--split", "val"]) == 0
    err = capsys.readouterr().err
    assert "armless.bvh" in err and "same bytes as" in err
    splits = json.loads((tmp_path / "ds" / "manifest.json").read_text())["splits"]
    subjects = {name: {s["subject"] for s in split["sources"]} for name, split in splits.items()}
    assert subjects["train"] and subjects["val"] and not subjects["train"] & subjects["val"]
    record = splits["train"]["motion_library"]["subject_split"]
    assert record["subjects"]["val"] == sorted(subjects["val"])
    licences = {s["licence"] for split in splits.values() for s in split["sources"]}
    assert "not given: pass --licence with the terms of these files" in licences  # AMASS brings its own
    assert np.isclose(sum(record["hours"].values()), (4 * 2.5 + 2.0) / 3600, rtol=0.01)


def test_synth_mixes_one_subjects_legs_with_anothers_arms(tmp_path, capsys):
    lib = _library(tmp_path / "lib")
    args = ["synth", "--motion", str(lib), "--mixed", "3", "--no-files", "--seed", "4", "--seconds", "2",
            "--resolution", "64x48", "--no-progress"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    split = json.loads((tmp_path / "a" / "manifest.json").read_text())["splits"]["train"]
    assert split["mixed"] == 3 and len(split["sources"]) == 3  # and no file synthesised as it is
    for source in split["sources"]:
        legs, upper = source["subjects"]
        assert source["source"].startswith("mixed:") and legs != upper
    a, b = (tmp_path / x / "train" / "shard-00000.npz" for x in "ab")
    assert a.read_bytes() == b.read_bytes()
    one = ["synth", "--motion", str(lib / "alice"), "--mixed", "1", "--out", str(tmp_path / "c")]
    assert main(one) == 2 and "--mixed needs two" in capsys.readouterr().err
