"""ajtwin._jax's XLA flags: added before JAX starts, never over the user's own."""

import os
import subprocess
import sys

import pytest

from ajtwin._jax import SMALL_LOOP_BYTES, xla_flags

THRESHOLD = "xla_cpu_small_while_loop_byte_threshold"


def test_defaults_on_x86_and_elsewhere():
    flags = xla_flags("", None, "x86_64").split()
    assert f"--xla_backend_extra_options={THRESHOLD}={SMALL_LOOP_BYTES}" in flags
    assert "--xla_cpu_max_isa=AVX" in flags
    # AVX is an x86 ISA name: elsewhere XLA would take it for a CPU target it is not
    assert xla_flags("", None, "aarch64") == (
        f"--xla_backend_extra_options={THRESHOLD}={SMALL_LOOP_BYTES}"
    )


def test_user_flags_win_and_are_kept():
    user = f"--xla_backend_extra_options={THRESHOLD}=64 --xla_cpu_max_isa=AVX512"
    assert xla_flags(user, None, "x86_64") == user
    # an unrelated user flag is kept, after ours (so a later duplicate of it would win too)
    flags = xla_flags("--xla_dump_to=/tmp/d", "2048", "AMD64").split()
    assert flags[-1] == "--xla_dump_to=/tmp/d"
    assert f"--xla_backend_extra_options={THRESHOLD}=2048" in flags


def test_override_zero_leaves_xla_default_and_negative_is_refused():
    assert THRESHOLD not in xla_flags("", "0", "x86_64")
    with pytest.raises(ValueError):
        xla_flags("", "-1", "x86_64")


def test_set_in_a_new_process_before_jax_starts():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["AJTWIN_XLA_SMALL_LOOP_BYTES"] = "4096"
    code = "import os, ajtwin._jax as j; print(os.environ['XLA_FLAGS'])"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout
    assert f"{THRESHOLD}=4096" in out
