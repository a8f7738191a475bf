"""The command line's one progress printer (cli/common.Progress): plain lines at a sensible rate in a log
file, one redrawn line per stage on a terminal; its adapters for the trainer and pose recovery."""
import io

from neumesh_core.cli.common import Progress
from neumesh_core.reconstruct.poses import PosesProgress
from neumesh_core.train.trainer import TrainProgress


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _printer(tty, **kw):
    out, clock = io.StringIO(), Clock()
    return Progress(out, tty=tty, clock=clock, **kw), out, clock


def test_a_log_file_gets_a_line_per_tenth_of_a_stage_and_its_end():
    p, out, clock = _printer(tty=False)
    for i in range(201):                     # a callback 200 times through the stage, 0.1 s apart
        clock.t = i * 0.1
        assert p.update("training", i / 200, f"step {i}") is True
    p.end()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert lines[0].startswith("[training]   0%  step 0")
    assert [ln.split()[1] for ln in lines[:-1]] == [f"{10 * k}%" for k in range(11)]
    assert lines[-1] == "[training] done in 0:00:20"


def test_a_slow_stage_gets_a_line_every_30_seconds_not_silence():
    p, out, clock = _printer(tty=False)
    p.update("poses: cameras", 0.0, "0 of 50 cameras placed")
    for s in range(1, 95):                   # 94 s stuck below the next tenth
        clock.t = float(s)
        p.update("poses: cameras", 0.05, "2 of 50 cameras placed")
    lines = out.getvalue().splitlines()
    assert len(lines) == 4                   # the start, then at 30, 60 and 90 s
    assert lines[-1] == "[poses: cameras]   5%  2 of 50 cameras placed  (0:01:30)"


def test_a_new_stage_ends_the_last_and_messages_go_between():
    p, out, clock = _printer(tty=False)
    p.update("scaffold: hull", 0.5)
    clock.t = 12.0
    p.update("scaffold: mesh", 0.0)
    p.say("scaffold (hull): 2000 vertices")
    p.end("reported")
    p.end()                                  # nothing open: nothing printed
    assert out.getvalue().splitlines() == [
        "[scaffold: hull]  50%  (0:00:00)", "[scaffold: hull] done in 0:00:12",
        "[scaffold: mesh]   0%  (0:00:00)", "scaffold (hull): 2000 vertices",
        "[scaffold: mesh] done in 0:00:00: reported"]


def test_a_terminal_redraws_one_line_per_stage():
    p, out, clock = _printer(tty=True, redraw_s=0.2)
    for i in range(101):                     # 100 callbacks in 1 s: redrawn at most every 0.2 s or per tenth
        clock.t = i * 0.01
        p.update("evaluation", i / 100, f"{i} of 100 views")
    p.say("a message")
    p.update("rendering", 0.5)
    p.end()
    lines = out.getvalue().split("\n")
    first = lines[0].split("\r")[1:]
    assert len(first) == 11                  # redrawn once per tenth (each within 0.2 s)
    assert first[0].startswith("[evaluation] -------------------- ")
    assert first[-1].startswith("[evaluation] #################### 100%  100 of 100 views")
    # the message below the stage's line; the stage ends on the next line when the next one starts
    assert lines[1:3] == ["a message", "\r[evaluation] done in 0:00:01"]
    assert lines[3].split("\r")[-1].rstrip() == "[rendering] done in 0:00:00" and lines[4:] == [""]


def test_training_shows_the_time_budget_when_it_ends_the_run():
    p, out, _ = _printer(tty=False)
    p.training(TrainProgress(step=120, total_steps=100_000, loss=0.01, psnr=21.5, rays_per_sec=18200, elapsed_s=60,
                             eta_s=120, samples_per_ray=12.0, fraction=1 / 3, limit="time"))
    p.training(TrainProgress(step=2000, total_steps=3000, loss=0.01, psnr=25.0, rays_per_sec=18200, elapsed_s=200,
                             eta_s=100, fraction=2 / 3, limit="steps"))
    a, b = out.getvalue().splitlines()
    assert a.startswith("[training]  33%  step 120 (0:03:00 budget)  loss 0.0100  psnr 21.50  18.2k rays/s")
    assert a.endswith("eta 0:02:00  (0:00:00)") and "100000" not in a
    assert b.startswith("[training]  67%  step 2000/3000  loss") and "eta 0:01:40" in b


def test_pose_recovery_stages_are_the_printer_stages():
    p, out, clock = _printer(tty=False)
    p.poses(PosesProgress("extract", 0.15, "features in 25 of 50 photos", 10.0, 0, 0.5))
    clock.t = 40.0
    p.poses(PosesProgress("match", 0.3, "0 of 1225 photo pairs matched (exhaustive)", 40.0, 0, 0.0))
    assert out.getvalue().splitlines() == [
        "[poses: features]  50%  features in 25 of 50 photos  (0:00:00)", "[poses: features] done in 0:00:40",
        "[poses: matching]   0%  0 of 1225 photo pairs matched (exhaustive)  (0:00:00)"]
