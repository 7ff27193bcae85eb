import io

from sb3_collapse.common import progress
from sb3_collapse.common.progress import on_terminal, progress_bar


def test_a_bar_draws_on_a_terminal_only_and_elsewhere_says_one_line(monkeypatch, capsys):
    assert list(progress_bar((i for i in range(3)), "reading", "trial")) == [0, 1, 2]  # a generator, counted first
    assert capsys.readouterr().err == "reading: 3 trials\n"  # captured stderr: not a terminal
    with progress_bar(None, "trials", "trial", total=2) as bar:  # updated by hand
        bar.update(2)
    assert capsys.readouterr().err == "trials: 2 trials\n"
    assert list(progress_bar([1, 2], "quiet", "item", progress=False)) == [1, 2]
    assert capsys.readouterr().err == "" and not on_terminal()

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    terminal = Terminal()
    monkeypatch.setattr(progress.sys, "stderr", terminal)
    assert on_terminal() and not on_terminal(False)
    assert list(progress_bar(range(3), "reading", "trial")) == [0, 1, 2]
    assert "\r" in terminal.getvalue() and "3/3" in terminal.getvalue()  # tqdm's frames, on the terminal


def test_the_sweeps_wait_for_its_trials_draws_no_bar_into_a_captured_stderr(tmp_path, capfd, monkeypatch):
    from sb3_collapse.sweep import runner

    class FakeRay:  # trial "a" finishes, trial "b" fails
        def wait(self, refs, num_returns, timeout):
            return [refs[0]], []

        def get(self, ref):
            return {"status": "finished"} if ref == "a" else {"status": "failed", "error": "boom"}

    monkeypatch.setattr(runner, "trial_dir", lambda out, trial: out / trial)
    summary = runner.SweepSummary(["a", "b"], [], [], {})
    runner._wait_for_trials(FakeRay(), {"a": "a", "b": "b"}, tmp_path, summary, True)  # the progress on
    assert summary.finished == ["a"] and list(summary.failed) == ["b"]
    captured = capfd.readouterr()
    assert captured.err == "trials: 2 trials\n"  # one line, no bar frames
    assert "FAILED b: boom" in captured.out and "\r" not in captured.out
