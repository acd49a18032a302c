"""difstar._compiler_flags: XLA_FLAGS gets the quick-compile flags only where they can act
and are known, never over the user's own setting; a process with them computes."""

import json
import os
import subprocess
import sys

from difstar import _compiler_flags as cf

_CHILD = """
import json, os, sys
import difstar
on = difstar.use_quick_compile_flags()
import jax.numpy as jnp
value = float(jnp.sum(jnp.arange(4.0) ** 2))  # XLA starts with these flags
print(json.dumps({"on": on, "flags": os.environ.get("XLA_FLAGS"), "value": value}))
"""


def _child(**env):
    base = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", cf.ENV)}
    out = subprocess.run([sys.executable, "-c", _CHILD], env=base | env, capture_output=True,
                         text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_fresh_process_gets_the_flags_and_computes():
    r = _child()
    assert r["value"] == 14.0
    if cf._jaxlib_version() in cf.CHECKED:
        assert r["on"] is True
        assert r["flags"] == "--xla_cpu_use_fusion_emitters=false"
    else:  # a jaxlib they were not checked on: XLA_FLAGS left alone
        assert r["on"] is False and r["flags"] is None


def test_the_users_own_setting_stands_and_off_turns_them_off():
    r = _child(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
    assert r["flags"] == "--xla_cpu_use_fusion_emitters=true" and r["value"] == 14.0
    r = _child(**{cf.ENV: "off"})
    assert r["on"] is False and r["flags"] is None


def test_nothing_changes_once_the_backend_has_started_or_on_an_unchecked_jaxlib(
        monkeypatch):
    import jax.numpy as jnp

    jnp.zeros(1).block_until_ready()  # the backend is running in this process
    before = os.environ.get("XLA_FLAGS")
    assert cf.use_quick_compile_flags() is False
    assert os.environ.get("XLA_FLAGS") == before
    monkeypatch.setattr(cf, "_backend_started", lambda: False)
    monkeypatch.setattr(cf, "_jaxlib_version", lambda: (99, 0))
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert cf.use_quick_compile_flags() is False
    assert "XLA_FLAGS" not in os.environ
