"""A config or scenario the CLI cannot use ends it with exit 2 and one message naming the file or the field, never a
traceback (exit 1): bytes that are not UTF-8, nesting deep enough to exhaust the stack, a 10 000-digit integer, an
'extends' chain of 1 500 files, a file with no key, a run whose trace would not fit in memory."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SCENARIOS

from clients.cli import main
from schemas.scenario import load_scenario

CONST = str(SCENARIOS / "paper-constant-load.toml")
NET = str(SCENARIOS / "network" / "radial-16.toml")


def _refused(capsys, argv: list[str], *needles: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("energyctl: ")
    for n in needles:
        assert n in err, err


BAD_FILES = {
    "not-utf8": (b'name = "\xff\xfe"\n', "is not UTF-8 text"),
    "deep-array": (("a = " + "[" * 2000 + "]" * 2000 + "\n").encode(), "nested deeper than 16 levels"),
    "deep-inline-table": (("a = " + "{b = " * 600 + "1" + "}" * 600 + "\n").encode(), "nested deeper than 16 levels"),
    "huge-integer": (("seed = " + "9" * 10_000 + "\n").encode(), "not valid TOML"),
    "empty": (b"", "is empty"),
    "only-comments": (b"# nothing here\n\n", "is empty"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
@pytest.mark.parametrize("command", ["sim", "sweep", "run", "plant", "load"])
def test_a_bad_file_exits_2_with_its_name(tmp_path, capsys, case, command):
    text, says = BAD_FILES[case]
    p = tmp_path / f"{case}.toml"
    p.write_bytes(text)
    argv = {"sim": ["sim", str(p)], "sweep": ["sweep", str(p), "--grid", "load.value=300.0", "--jobs", "1"],
            "run": ["run", "--config", str(p)], "plant": ["plant", "--config", str(p)],
            "load": ["load", "--config", str(p)]}[command]
    _refused(capsys, argv, str(p.name), says)


def test_a_long_extends_chain_exits_2(tmp_path, capsys):
    for k in range(1500):
        (tmp_path / f"c{k}.toml").write_text(f'extends = "c{k + 1}.toml"\n' if k < 1499 else 'id = "c"\n')
    _refused(capsys, ["run", "--config", str(tmp_path / "c0.toml")], "'extends' chains more than 8 files")


def test_a_short_extends_chain_still_works(tmp_path):
    from schemas.component import ComponentConfig, load_config

    (tmp_path / "base.toml").write_text('id = "c"\n[controller]\nK_per_s = 900\n')
    (tmp_path / "mid.toml").write_text('extends = "base.toml"\n[controller]\nv_ref_V = 81\n')
    (tmp_path / "top.toml").write_text('extends = "mid.toml"\nid = "top"\n')
    cfg = load_config(ComponentConfig, tmp_path / "top.toml")
    assert (cfg.id, cfg.controller.K_per_s, cfg.controller.v_ref_V) == ("top", 900.0, 81.0)


@pytest.mark.parametrize(("value", "says"), [
    ("9" * 5000, "not valid TOML"),
    ("[" * 3000, "nested deeper than 16 levels"),
    ("9" * 4000, "seed: Input should be less than or equal to"),  # parsed, refused by its bound, shown cut short
], ids=["5000-digits", "3000-brackets", "4000-digits"])
def test_a_bad_set_value_exits_2(capsys, value, says):
    _refused(capsys, ["sim", CONST, "--set", f"seed={value}"], says)
    assert main(["sim", CONST, "--set", f"seed={value}"]) == 2
    assert len(capsys.readouterr().err) < 400  # the value is not echoed whole


@pytest.mark.parametrize(("path", "sets", "says"), [
    (CONST, ["timing.duration_s=3600", "timing.control_rate_hz=100000"], "360,000,000 samples of 29 values"),
    (NET, ["timing.duration_s=3600"], "samples of 280 values"),
])
def test_a_run_too_long_to_hold_exits_2_before_it_starts(capsys, path, sets, says):
    """3600 s at 100 kHz grew ~230 MB/s until a MemoryError: refused at once, naming the two keys."""
    argv = ["sim", path]
    for s in sets:
        argv += ["--set", s]
    _refused(capsys, argv, says, "timing.duration_s x timing.control_rate_hz", "GiB")


def test_the_trace_is_the_same_whichever_chunk_it_is_gathered_in(monkeypatch):
    """The offline run moves its samples into the trace's columns every CHUNK samples (memory: 232 B a sample, not a
    Python tuple's ~1 KB); a trace gathered 7 at a time equals one gathered in one go."""
    import service.sim as sim

    scn = load_scenario(CONST, ["timing.duration_s=0.02"])
    whole = sim.run(scn)
    monkeypatch.setattr(sim, "CHUNK", 7)
    chunked = sim.run(scn)
    assert len(whole.trace["t"]) == 200
    for f in sim.TRACE_FIELDS:
        assert np.array_equal(whole.trace[f], chunked.trace[f], equal_nan=True), f
    assert whole.metrics == chunked.metrics
