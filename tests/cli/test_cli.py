import json
import os
import subprocess
import sys

import pytest

from neumesh_core.cli import build_parser, main


@pytest.mark.parametrize("cmd", ["train", "render", "eval", "demo"])
def test_help_explains_every_option(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    parser = build_parser()
    sub = parser._subparsers._group_actions[0].choices[cmd]
    for action in sub._actions:
        if action.option_strings and action.dest != "help":
            assert action.help, f"{cmd} {action.option_strings} has no help"
    assert "--" in out


def test_bad_training_options_are_an_error_not_a_traceback(small_scene_dir, tmp_path, capsys):
    field = str(tmp_path / "f.neumesh")
    assert main(["train", "--data", small_scene_dir, "--out", field, "--steps", "5",
                 "--code-levels-until", "0.3"]) == 2
    err = capsys.readouterr().err
    assert "error: training options:" in err and "code_levels is 0" in err
    assert not os.path.exists(field)


def test_train_render_eval_on_the_small_scene(small_scene_dir, tmp_path, capsys):
    field = str(tmp_path / "f.neumesh")
    assert main(["train", "--data", small_scene_dir, "--out", field, "--steps", "30", "--rays", "512",
                 "--lr-final", "0.3", "--average-from", "0.5", "--no-eval"]) == 0
    assert os.path.exists(field)
    assert "weights averaged over" in capsys.readouterr().err
    assert main(["eval", "--field", field, "--data", small_scene_dir, "--split", "val",
                 "--json", str(tmp_path / "e.json")]) == 0
    r = json.load(open(tmp_path / "e.json"))
    assert r["n_views"] == 4 and r["mean"]["psnr"] > 10 and r["lpips_available"] in (True, False)
    assert main(["eval", "--field", field, "--data", small_scene_dir, "--split", "val", "--supersample", "2",
                 "--step-scale", "0.2", "--json", str(tmp_path / "e2.json")]) == 0
    r2 = json.load(open(tmp_path / "e2.json"))
    p1, p2 = r["mean"]["psnr"], r2["mean"]["psnr"]
    assert r2["n_views"] == 4 and p2 != p1 and abs(p2 - p1) < 3
    assert main(["render", "--field", field, "--out", str(tmp_path / "tt"), "--frames", "2",
                 "--resolution", "24x16", "--supersample", "2"]) == 0
    assert sorted(os.listdir(tmp_path / "tt")) == ["frame_0000.png", "frame_0001.png"]



def test_render_takes_the_held_out_split_a_dataset_has(tmp_path, capsys):
    """`neumesh render --data` on a dataset without a 'test' split (a phone capture holds out 'val')
    renders 'val' by default, and a split the dataset lacks is an error that names the ones it has
    (it was a KeyError traceback)."""
    from neumesh_core.data.synthetic import make_default_scene

    d = tmp_path / "s"
    make_default_scene(str(d), resolution=16, n_train=4, n_val=2, n_test=0)
    os.remove(d / "transforms_test.json")
    field = str(tmp_path / "f.neumesh")
    assert main(["train", "--data", str(d), "--out", field, "--steps", "2", "--rays", "64", "--no-eval"]) == 0
    assert main(["render", "--field", field, "--data", str(d), "--out", str(tmp_path / "v")]) == 0
    assert sorted(os.listdir(tmp_path / "v")) == ["frame_0000.png", "frame_0001.png"]
    capsys.readouterr()
    assert main(["render", "--field", field, "--data", str(d), "--split", "test", "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert "no 'test' split" in err and "train, val" in err and "Traceback" not in err

def test_train_without_mesh_says_what_to_do(tmp_path, capsys):
    from neumesh_core.data.synthetic import make_default_scene

    d = tmp_path / "s"
    make_default_scene(str(d), resolution=16, n_train=4, n_val=1, n_test=1)
    os.remove(d / "mesh.ply")
    assert main(["train", "--data", str(d), "--out", str(tmp_path / "x.neumesh")]) == 2
    assert "neumesh scaffold" in capsys.readouterr().err


def test_bad_data_path_is_a_clear_error(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "x")]) == 2
    assert "error:" in capsys.readouterr().err


def test_console_script_entry_point():
    r = subprocess.run([sys.executable, "-m", "neumesh_core.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "demo" in r.stdout


def test_fit_runs_every_stage_and_resumes(tmp_path, capsys):
    """Every stage, then a resumed run. Stderr (not a terminal here) gets plain lines for each stage:
    where it starts, how far it got, when it ended; no carriage returns."""
    from neumesh_core.data.synthetic import make_default_scene

    d = tmp_path / "s"
    make_default_scene(str(d), resolution=32, n_train=12, n_val=2, n_test=1, mesh_subdiv=3)
    out = tmp_path / "fit"
    common = ["fit", "--data", str(d), "--out", str(out), "--vertices", "2000", "--resolution", "64",
              "--rays", "256", "--no-metrics"]
    assert main(common + ["--steps", "4"]) == 0
    s1 = json.load(open(out / "fit.json"))
    assert not s1["scaffold"]["reused"] and s1["train"]["steps"] == 4 and "psnr" in s1["eval"]
    err = capsys.readouterr().err
    assert "\r" not in err
    for stage in ("scaffold: hull", "scaffold: mesh", "training", "evaluation"):
        lines = [ln for ln in err.splitlines() if ln.startswith(f"[{stage}] ")]
        assert len(lines) >= 2 and " done in " in lines[-1], (stage, err)
    assert "[training] 100%  step 4/4  loss" in err and "[evaluation] done in" in err and "psnr" in err
    assert main(common + ["--steps", "8"]) == 0
    s2 = json.load(open(out / "fit.json"))
    assert s2["scaffold"]["reused"] and s2["resumed_from_step"] == 4 and s2["train"]["steps"] == 8


def test_demo_main_job_end_to_end(tmp_path, monkeypatch, capsys):
    """The README's third command, with a tiny budget (the real default trains longer)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "demo"
    assert main(["demo", "--small", "--steps", "30", "--rays", "512", "--frames", "2", "--out", str(out)]) == 0
    r = json.load(open(out / "eval.json"))
    assert r["n_views"] >= 1 and r["mean"]["psnr"] > 10
    assert sorted(os.listdir(out / "turntable")) == ["frame_0000.png", "frame_0001.png"]
    assert (out / "comparison.png").exists() and (out / "field.neumesh").exists()
    assert "test PSNR" in capsys.readouterr().out
    assert (tmp_path / "cache" / "neumesh").exists()  # the scene was made in the cache, not in $HOME
