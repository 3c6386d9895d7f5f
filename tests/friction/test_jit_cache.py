"""Compile on demand and an honest numba cache key (``stagectl.jit``), checked in fresh interpreters.

Each test runs a real subprocess with its own empty ``NUMBA_CACHE_DIR``: importing must compile nothing, and
a cached kernel must be rebuilt when a kernel it inlines from *another* module changes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path


def _run(code: str, cache: Path, extra_path: Path | None = None, env: dict[str, str] | None = None) -> str:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONDONTWRITEBYTECODE="1", **(env or {}))
    if extra_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(extra_path), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


def test_importing_friction_and_plant_compiles_nothing(tmp_path: Path) -> None:
    got = json.loads(_run("""
        import json
        import stagectl.friction, stagectl.sim.plant
        from stagectl.friction import _numba, dahl, effects, gms, hsieh, lugre, maxwell, static
        from stagectl.sim import plant
        mods = (_numba, dahl, effects, gms, hsieh, lugre, maxwell, static, plant)
        import sys
        numba_imported = "numba" in sys.modules  # kernels are LazyKernels: numba comes with the first compiled use
        n = {m.__name__: sum(len(d.overloads) for d in vars(m).values() if hasattr(d, "overloads"))
             for m in mods}
        import os
        files = [f for _, _, fs in os.walk(os.environ["NUMBA_CACHE_DIR"]) for f in fs]
        print(json.dumps({"compiled": n, "cache_files": len(files), "numba_imported": numba_imported}))
    """, tmp_path / "nc"))
    assert got["compiled"] and all(v == 0 for v in got["compiled"].values()), got
    assert got["cache_files"] == 0
    assert got["numba_imported"] is False


def test_using_one_model_compiles_only_that_model(tmp_path: Path) -> None:
    got = json.loads(_run("""
        import json
        from stagectl.friction import build, dahl, gms, lugre
        m = build({"model": "dahl", "sigma0_n_m": 1e5, "fc_n": 1.0})
        st = m.initial_state()
        m.step(st, 1e-9, 1e-5, 1e-4)
        print(json.dumps({"dahl": len(dahl._kstep.overloads), "gms": len(gms._kstep.overloads),
                          "lugre": len(lugre._kstep.overloads)}))
    """, tmp_path / "nc"))
    assert got == {"dahl": 1, "gms": 0, "lugre": 0}


def test_the_sim_configs_plant_and_feed_forward_compile_only_what_they_use(tmp_path: Path) -> None:
    """What ``stagectl run --config config/sim.yaml`` compiles from an empty cache: the GMS step (the feed-forward
    calls it) and the plant's per-cycle step, which calls that same compiled step; not the force
    kernel, not the plain or general ``simulate`` loops, no other model."""
    repo = Path(__file__).resolve().parents[2]
    got = json.loads(_run(f"""
        import json, sys
        from stagectl.config import load_app_config
        from stagectl.friction import gms, lugre
        from stagectl.sim import plant
        cfg = load_app_config({str(repo / "config" / "sim.yaml")!r})
        p = plant.StagePlant(cfg.sim.plant)
        ff = cfg.controller.feedforward.model.friction
        ff.step(ff.initial_state(), 1e-9, 1e-4, 1e-3)
        p.step(0.5, 1e-3)
        from stagectl.jit import dispatcher
        plain, integ, kstep = plant._LOOPS[id(dispatcher(gms._kstep))][0:2] + (gms._kstep,)
        print(json.dumps({{"step": len(kstep.overloads), "force": len(gms._kforce.overloads),
                          "cycle": len(p._cycle.overloads),
                          "plain": len(plain.overloads), "general": len(integ.overloads),
                          "lugre": len(lugre._kstep.overloads), "scipy_linalg": "scipy.linalg" in sys.modules}}))
    """, tmp_path / "nc"))
    assert got == {"step": 1, "force": 0, "cycle": 1, "plain": 0, "general": 0,
                   "lugre": 0, "scipy_linalg": False}


def test_second_process_loads_from_the_cache_dir(tmp_path: Path) -> None:
    code = """
        import json
        from stagectl.friction import build, gms
        from stagectl.jit import loaded_from_cache
        m = build({"model": "gms", "k_n_m": [1e5], "alpha": [1.0], "fc_n": 1.0, "fs_n": 1.2})
        m.step(m.initial_state(), 1e-9, 1e-5, 1e-4)
        print(json.dumps({"hits": loaded_from_cache(gms._kstep)}))
    """
    cache = tmp_path / "nc"
    assert json.loads(_run(code, cache)) == {"hits": 0}
    assert any(cache.rglob("*.nbi"))
    assert json.loads(_run(code, cache)) == {"hits": 1}


def test_cache_dir_order(tmp_path: Path) -> None:
    code = "from stagectl.jit import cache_dir; print(cache_dir())"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CACHE_DIRECTORY", "XDG_CACHE_HOME")}

    def where(**extra: str) -> str:
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             check=True)
        return out.stdout.strip()

    assert where(NUMBA_CACHE_DIR=str(tmp_path / "a"), CACHE_DIRECTORY=str(tmp_path / "b")) == str(tmp_path / "a")
    assert where(CACHE_DIRECTORY=f"{tmp_path / 'b'}:{tmp_path / 'c'}") == str(tmp_path / "b" / "numba")
    assert where(XDG_CACHE_HOME=str(tmp_path / "x")) == str(tmp_path / "x" / "stagectl" / "numba")


def test_editing_an_inlined_kernel_of_another_module_recompiles_its_caller(tmp_path: Path) -> None:
    """The trap numba has by itself: ``outer`` (module b) inlines ``inner`` (module a); a cached ``outer``
    ignores an edit of a.py. With :func:`stagectl.jit.kernel` the key holds a.py's source hash."""
    pkg = tmp_path / "src"
    pkg.mkdir()
    (pkg / "jit_a.py").write_text(textwrap.dedent("""
        from stagectl.jit import kernel

        @kernel(inline="always")
        def inner(x):
            return x + 1.0
    """))
    (pkg / "jit_b.py").write_text(textwrap.dedent("""
        from stagectl.jit import kernel
        import jit_a

        @kernel
        def outer(x):
            return 2.0 * jit_a.inner(x)
    """))
    code = """
        import json, jit_b
        from stagectl.jit import loaded_from_cache
        r = jit_b.outer(1.0)
        print(json.dumps({"r": r, "hits": loaded_from_cache(jit_b.outer)}))
    """
    cache = tmp_path / "nc"
    assert json.loads(_run(code, cache, pkg)) == {"r": 4.0, "hits": 0}
    assert json.loads(_run(code, cache, pkg)) == {"r": 4.0, "hits": 1}
    (pkg / "jit_a.py").write_text((pkg / "jit_a.py").read_text().replace("x + 1.0", "x + 3.0"))
    assert json.loads(_run(code, cache, pkg)) == {"r": 8.0, "hits": 0}


def test_dependency_files_follow_the_plant_into_effects_and_helpers() -> None:
    from stagectl.friction import _numba, effects, gms
    from stagectl.jit import dependency_files
    from stagectl.sim import plant

    integrate, _ = plant.loops_for(gms._kstep)
    deps = dependency_files(integrate.py_func)
    assert effects.__file__ in deps  # inlined modifiers
    assert gms.__file__ in deps  # the model kernel held in the closure
    assert _numba.__file__ in deps  # and what that one inlines (transitively)
    assert plant.__file__ not in deps


def test_stagectl_warm_fills_the_cache_the_next_start_loads(tmp_path: Path) -> None:
    """``stagectl warm --config`` compiles the kernels of the configured model and plant into an empty cache;
    a second warm (a start after install) loads every one of them instead of compiling."""
    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "nc"))
    cmd = [sys.executable, "-m", "stagectl.cli", "warm", "--config", str(repo / "config" / "sim.yaml")]

    def warm() -> dict[str, object]:
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        return dict(json.loads(out.stdout.strip().splitlines()[-1]))

    first = warm()
    assert first["cache_dir"] == str(tmp_path / "nc")
    assert first["models"] == ["gms"] and first["plants"] == 1
    assert first["kernels"] == 4 and first["loaded_from_cache"] == 0  # step, force, per-cycle step, plain loop
    second = warm()
    assert second["loaded_from_cache"] == second["signatures"] == first["signatures"]


def test_stagectl_warm_on_a_real_stage_config_warms_nothing_and_imports_no_numba(tmp_path: Path) -> None:
    """A real stage (``io.kind: canopen``, no ``sim:``) steps its feed-forward as plain Python: the unit's
    ``ExecStartPre`` warm has nothing to compile or load, and does not import numba."""
    repo = Path(__file__).resolve().parents[2]
    code = ("import json, sys\nfrom stagectl.cli import main\n"
            f"main(['warm', '--config', {str(repo / 'config' / 'stage-canopen.yaml')!r}])\n"
            "print(json.dumps({'numba': 'numba' in sys.modules}))\n")
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "nc")),
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    got = json.loads(lines[-2])
    assert got["kernels"] == 0 and got["models"] == [] and got["plain_feedforward"] == [
        str(repo / "config" / "stage-canopen.yaml")]
    assert json.loads(lines[-1]) == {"numba": False}


def test_a_constant_imported_from_another_module_is_part_of_the_key(tmp_path: Path) -> None:
    """numba freezes global constants into the machine code; one imported from another module changes the
    compiled result, so its value is in the key."""
    pkg = tmp_path / "src"
    pkg.mkdir()
    (pkg / "jit_c.py").write_text("SCALE = 2.0\n")
    (pkg / "jit_d.py").write_text(textwrap.dedent("""
        from stagectl.jit import kernel
        from jit_c import SCALE

        @kernel
        def scaled(x):
            return SCALE * x
    """))
    code = """
        import json, jit_d
        from stagectl.jit import loaded_from_cache
        print(json.dumps({"r": jit_d.scaled(1.5), "hits": loaded_from_cache(jit_d.scaled)}))
    """
    cache = tmp_path / "nc"
    assert json.loads(_run(code, cache, pkg)) == {"r": 3.0, "hits": 0}
    assert json.loads(_run(code, cache, pkg)) == {"r": 3.0, "hits": 1}
    (pkg / "jit_c.py").write_text("SCALE = 4.0\n")
    assert json.loads(_run(code, cache, pkg)) == {"r": 6.0, "hits": 0}


def test_identification_kernels_use_the_stagectl_cache_dir(tmp_path: Path) -> None:
    """stagectl.ident's compiled loops are declared with ``kernel`` like every other: without
    ``NUMBA_CACHE_DIR`` they are cached under ``$XDG_CACHE_HOME/stagectl/numba`` (not in ``__pycache__`` next
    to the source, which an installed package may not be allowed to write), and a second process loads them."""
    code = """
        import json
        import numpy as np
        from stagectl.ident._kernels import first_order_lag, maxwell_unit_states
        from stagectl.jit import loaded_from_cache
        maxwell_unit_states(np.linspace(0.0, 1e-5, 50), np.array([1e-6, 3e-6]))
        first_order_lag(np.ones(20), 1e-3, 1e-2, 0.0)
        print(json.dumps({"hits": loaded_from_cache(maxwell_unit_states) + loaded_from_cache(first_order_lag)}))
    """
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CACHE_DIRECTORY")}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONDONTWRITEBYTECODE="1")

    def run() -> dict[str, int]:
        out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout.strip().splitlines()[-1])

    assert run() == {"hits": 0}
    cached = {p.name.split(".")[1].split("-")[0] for p in (tmp_path / "xdg" / "stagectl" / "numba").rglob("*.nbi")}
    assert {"maxwell_unit_states", "first_order_lag"} <= cached, cached
    assert run() == {"hits": 2}


def test_threads_that_first_use_a_kernel_together_share_one_dispatcher(tmp_path: Path) -> None:
    """The first compiled use from two threads at once (the daemon's loop thread and another) makes one dispatcher:
    each extra one would compile the kernel again, and the module's class attributes would hold another object
    than the kernel's own. A fresh interpreter, so the first trial also races numba's own import."""
    (tmp_path / "racemod.py").write_text("def f(x):\n    return x + 1.0\n")
    got = json.loads(_run("""
        import json, threading
        from stagectl.jit import kernel
        from racemod import f

        distinct = []
        for _ in range(40):
            k = kernel(f)
            bar = threading.Barrier(4)
            got = []

            def run():
                bar.wait()
                got.append(k.dispatcher())

            ts = [threading.Thread(target=run) for _ in range(4)]
            for t in ts:
                t.start()
            for t in ts:
                t.join()
            distinct.append(len({id(d) for d in got}))
        print(json.dumps(distinct))
    """, tmp_path / "cache", extra_path=tmp_path))
    assert got == [1] * 40, got  # on main: e.g. [4, 1, 2, 1, 1, 2, ...]
