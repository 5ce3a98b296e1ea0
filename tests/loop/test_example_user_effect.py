"""``python examples/02_write_an_effect.py`` as a newcomer runs it (docs/writing_an_effect.md): the verdict reads
as plain text and the value printed as fitted is the one the verdict names. It printed the verdict's Markdown
('missing **range_offset**') and, as 'fitted', the screening fit's 0.0300 under a verdict saying 0.02988."""

import re
import subprocess
import sys

import pytest

from ..conftest import REPO


@pytest.mark.slow
def test_the_user_effect_example_prints_plain_text_and_the_verdicts_value(tmp_path):
    run = subprocess.run(
        [sys.executable, str(REPO / "examples" / "02_write_an_effect.py")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    assert "**" not in run.stdout, run.stdout
    named = re.search(r"missing range_offset \(offset=([-0-9.]+)\)", run.stdout)
    fitted = re.search(r"fitted on every ray[^\n]*'range_offset\.offset': \[([-0-9.]+)\]", run.stdout)
    assert named and fitted, run.stdout
    assert float(fitted.group(1)) == pytest.approx(float(named.group(1)), abs=1e-5)
    assert float(fitted.group(1)) == pytest.approx(0.03, abs=0.001)  # the hidden offset; sigma 0.01 m, 6,000 returns
