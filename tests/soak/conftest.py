"""Fixtures and helpers of the soak tests (deploy/soak.sh): the end-to-end tests' conftest
(tests/integration/conftest.py: vasl_scene's scene, binaries from $VASL_BUILD_DIR, a real vasld)
loaded by path and re-exported, so `from conftest import ...` works here as it does there, and
tests/integration on sys.path for crash_util. tests/soak is not collected by deploy/test.sh."""
from __future__ import annotations

import importlib.util
import os
import sys

_INTEGRATION = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "integration"))
if _INTEGRATION not in sys.path:
    sys.path.append(_INTEGRATION)

_spec = importlib.util.spec_from_file_location("vasl_integration_conftest",
                                               os.path.join(_INTEGRATION, "conftest.py"))
_integration = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = _integration
_spec.loader.exec_module(_integration)

# Re-export everything (fixtures included: pytest registers the fixtures a conftest holds).
for _name in dir(_integration):
    if not _name.startswith("__"):
        globals()[_name] = getattr(_integration, _name)


def env_int(name: str, default: int) -> int:
    """An integer setting of the soak from the environment."""
    value = os.environ.get(name, "")
    try:
        return int(value) if value else default
    except ValueError:
        raise SystemExit(f"{name}={value!r}: expected an integer") from None
