"""mtcw_bench.codeab: two code trees' chain times alternated."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mtcw_bench import codeab

ROOT = Path(codeab.__file__).resolve().parents[1]


def test_alternates_old_and_new_with_mean_and_median(capsys):
    """This tree against itself: every round runs old, then new, each a fresh process whose times
    are per frame (frames x repeats of them) and positive."""
    assert codeab.main(["--old", str(ROOT), "--scene", "cw-bench", "--samples", "16384", "--frames", "2",
                        "--repeats", "1", "--rounds", "2"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("round")]
    assert [r.split()[2] for r in rows] == ["old", "new", "old", "new"]
    for r in rows:
        nums = [float(v) for v in re.findall(r"(?:mean|median) ([0-9.]+)", r)]
        assert len(nums) == 4 and all(v > 0 for v in nums[:2]), r


def test_run_tree_gives_one_time_per_frame_and_pass():
    t = codeab.run_tree(ROOT, "cw-bench", "fast", 16384, 2, 2)
    assert len(t["total"]) == len(t["doppler"]) == 4
    assert all(d <= tot for d, tot in zip(t["doppler"], t["total"]))


def test_a_tree_without_the_chain_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        codeab.main(["--old", str(tmp_path)])
    assert "holds no mtcw_core/chain.py" in capsys.readouterr().err


def test_a_failing_chain_is_named_with_its_error(capsys):
    """An unknown scene: the child's own error is shown, and the run exits 1."""
    assert codeab.main(["--old", str(ROOT), "--scene", "no-such-scene", "--samples", "16384", "--frames", "2",
                        "--repeats", "1", "--rounds", "1"]) == 1
    err = capsys.readouterr().err
    assert "round 1 old" in err and "no-such-scene" in err and "failed" in err


@pytest.mark.parametrize("flag", ["--frames", "--repeats", "--rounds", "--samples"])
def test_counts_below_one_are_refused_by_name(flag, capsys):
    with pytest.raises(SystemExit):
        codeab.main(["--old", str(ROOT), flag, "0"])
    assert f"{flag}: must be at least 1" in capsys.readouterr().err
