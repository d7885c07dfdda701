"""What the README and `make run` quote from the seed study is what its committed output says."""

import csv
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "docs" / "seed_study"


def test_the_quoted_counts_are_the_committed_rows():
    with open(STUDY / "dry_to_snow.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    n = len(rows)
    base = sum(r["base_left_lane"] == "True" for r in rows)
    certified = sum(r["certified_left_lane"] == "True" for r in rows)
    unprotected = sum(float(r["certified_time_unprotected_s"]) > 0 for r in rows)
    summary = (STUDY / "dry_to_snow.md").read_text()
    assert (f"the base car left its lane in {base} of {n} drives, the certified car in "
            f"{certified} of {n} (time unprotected > 0 in {unprotected})") in summary
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert (f"the base car left its lane in {base} of {n} drives and the certified car in "
            f"{certified} of {n}") in readme
    peaks = [float(r["certified_peak_abs_e1_m"]) for r in rows]
    assert f"peak {min(peaks):.3f}-{max(peaks):.3f} m" in readme
    assert "grep -h \"left its lane\" docs/seed_study/dry_to_snow.md" in \
        (ROOT / "Makefile").read_text()
    assert re.search(r"seeds 1-(\d+)", summary).group(1) == str(n)
