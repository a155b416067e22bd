"""The client installs as a user installs it (issue "Real captures in"): `pip install
./clients/python` into a clean virtual environment, with nothing generated beforehand, gives a
working `vasl` command whose stubs talk to a real vasld."""
from __future__ import annotations

import os
import subprocess
import sys
import venv

from conftest import REPO


def test_pip_install_into_a_clean_venv_gives_a_working_cli(server, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    pip = env_dir / "bin" / "pip"
    r = subprocess.run([str(pip), "install", "--quiet", os.path.join(REPO, "clients", "python")],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"pip install failed:\n{r.stdout}\n{r.stderr}"
    vasl = env_dir / "bin" / "vasl"
    r = subprocess.run([str(vasl), "--server", server.address, "project", "create",
                        "installed-client"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"{r.stdout}\n{r.stderr}"
    r = subprocess.run([str(vasl), "--server", server.address, "project", "list"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "installed-client" in r.stdout, f"{r.stdout}\n{r.stderr}"
    # pye57 is a regular dependency: E57 files read without extra installs.
    r = subprocess.run([str(env_dir / "bin" / "python"), "-c", "import pye57, vasl.readers"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    print(f"\nclean venv at {env_dir}: pip install ./clients/python, vasl project create/list OK")
