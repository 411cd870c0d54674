"""Importing the package: MKL's reproducible mode."""

from __future__ import annotations

import os
import subprocess
import sys

# torch first, as the benchmarks import it: MKL reads its mode at its first call, not when torch loads
PROBE = "import os, torch, avatarperfect_cli; print(os.environ.get('MKL_CBWR'))"


def test_mkl_runs_in_its_reproducible_mode_unless_the_environment_chose_one() -> None:
    environment = {name: value for name, value in os.environ.items() if name != "MKL_CBWR"}
    for chosen, expected in ((None, "COMPATIBLE"), ("AVX2", "AVX2")):
        if chosen is not None:
            environment["MKL_CBWR"] = chosen
        result = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=300, env=environment)
        assert result.stdout.split() == [expected], result.stdout + result.stderr
