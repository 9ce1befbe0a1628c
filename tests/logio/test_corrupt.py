"""Log tools on damaged files: a corrupt chunk is named with its byte offset and skipped, the chunks after it are
still read, recover keeps every intact chunk and says what it dropped; empty and non-MCAP files are errors; exit
codes: log info 0 whole / 1 cut off or corrupt / 2 not a log; log recover 0 nothing lost but a cut-off tail / 1
corrupt chunks dropped / 2 nothing written; replay 0 identical / 1 diverged / 2 cannot replay (corrupt, not a log)."""

from __future__ import annotations

import json
import struct

import pytest
from conftest import SCENARIOS

from clients.cli import main
from schemas.scenario import load_scenario
from service.logio.mcapfile import write_sim_mcap
from service.logio.reader import _top_level, messages
from service.sim import run


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """A 0.3 s sim log (3000 ticks, 15 000 messages): three zstd chunks."""
    res = run(load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.3"]))
    path = tmp_path_factory.mktemp("corrupt") / "good.mcap"
    write_sim_mcap(path, res)
    data = path.read_bytes()
    chunks = [(c - 9, ln) for op, c, ln in _top_level(data) if op == 0x06]
    assert len(chunks) >= 3
    return path, data, chunks


def _info(path, capsys) -> tuple[int, dict]:
    rc = main(["log", "info", str(path), "--json"])
    return rc, json.loads(capsys.readouterr().out)


def _compressed_start(data: bytes, off: int) -> int:
    """Where a chunk's compressed bytes begin (record header, 3 x u64, crc, compression string, u64 length)."""
    comp_len = struct.unpack_from("<I", data, off + 9 + 28)[0]
    return off + 9 + 32 + comp_len + 8


def test_a_bit_flipped_chunk_is_named_skipped_and_recover_keeps_the_rest(sim_log, tmp_path, capsys):
    path, data, chunks = sim_log
    rc, whole = _info(path, capsys)
    assert rc == 0 and whole["intact"] and whole["messages"] == 15_000 and whole["damage"] == []
    off, ln = chunks[0]
    bad = bytearray(data)
    bad[off + 9 + ln // 2] ^= 0x10  # one bit in the middle of the first chunk's zstd data
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(bad)

    rc, got = _info(flipped, capsys)
    assert rc == 1 and not got["intact"]
    assert [(d["offset"], d["what"]) for d in got["damage"]] == [(off, "corrupt chunk")]
    lost = got["damage"][0]["messages"]
    assert lost > 0 and got["messages"] == 15_000 - lost  # the later chunks are all read
    assert main(["log", "info", str(flipped)]) == 1
    text = capsys.readouterr().out
    assert f"corrupt chunk at byte {off}" in text and "CORRUPT" in text

    assert main(["replay", str(flipped)]) == 2
    err = capsys.readouterr().err
    assert f"corrupt chunk at byte {off}" in err and "Traceback" not in err

    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(flipped), str(fixed)]) == 1
    out = capsys.readouterr()
    assert f"recovered {15_000 - lost} messages" in out.out and "already" not in out.out
    assert f"dropped corrupt chunk at byte {off}" in out.err and f"{lost} messages lost" in out.err
    rc, again = _info(fixed, capsys)  # the recovered file is whole and says what its original lost
    assert rc == 0 and again["messages"] == 15_000 - lost
    assert again["channels"] == got["channels"]
    assert [d["offset"] for d in again["recovered"]["dropped"]] == [off]
    # its first ticks are gone: the core's state at the first readable one is unknown
    assert main(["replay", str(fixed)]) == 2
    assert "lost its first ticks" in capsys.readouterr().err


def test_a_chunk_whose_zstd_frame_breaks_mid_file_replays_up_to_it_once_recovered(sim_log, tmp_path, capsys):
    path, data, chunks = sim_log
    off, _ln = chunks[1]
    bad = bytearray(data)
    bad[_compressed_start(data, off)] ^= 0xFF  # the zstd magic: the frame does not decompress at all
    broken = tmp_path / "zstd.mcap"
    broken.write_bytes(bad)
    rc, got = _info(broken, capsys)
    assert rc == 1 and got["damage"][0]["offset"] == off and "zstd" in got["damage"][0]["reason"]
    assert main(["replay", str(broken)]) == 2
    assert f"byte {off}" in capsys.readouterr().err
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(broken), str(fixed)]) == 1
    capsys.readouterr()
    assert main(["replay", str(fixed), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    start = got["damage"][0]["start_s"]
    assert res["identical"] and res["stopped_at_gap"]["offset"] == off
    assert 0 < res["compared"] == round(start * 10_000)  # every tick before the lost chunk, none after
    assert main(["replay", str(fixed)]) == 0
    assert f"compared up to t = {start:.6f} s only" in capsys.readouterr().out


def test_a_corrupt_chunk_length_resumes_at_the_next_chunk_the_summary_lists(sim_log, tmp_path, capsys):
    path, data, chunks = sim_log
    off, _ln = chunks[0]
    bad = bytearray(data)
    bad[off + 1 + 5] ^= 0x01  # the record length: 2^40 bytes more, past the end of the file
    broken = tmp_path / "length.mcap"
    broken.write_bytes(bad)
    rc, got = _info(broken, capsys)
    assert rc == 1 and got["complete"]
    assert [(d["offset"], d["what"]) for d in got["damage"]] == [(off, "unreadable record")]
    assert f"resumed at byte {chunks[1][0]}" in got["damage"][0]["reason"]
    assert 0 < got["messages"] < 15_000 and got["undeclared"] == 0  # the summary declared the channels


def test_empty_non_mcap_and_truncated_files(sim_log, tmp_path, capsys):
    path, data, chunks = sim_log
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    text = tmp_path / "notes.mcap"
    text.write_text("not a log at all\n" * 20)
    for f, why in ((empty, "empty file (0 bytes)"), (text, "not an MCAP file")):
        assert main(["log", "info", str(f)]) == 2
        assert why in capsys.readouterr().err
        assert main(["replay", str(f)]) == 2
        assert why in capsys.readouterr().err
        out = tmp_path / "out.mcap"
        assert main(["log", "recover", str(f), str(out)]) == 2 and not out.exists()
        assert why in capsys.readouterr().err
    assert messages(empty, "/meas") == []  # a log still being created reads as empty, not as an error

    cut_at = chunks[2][0] + 1000  # inside the third chunk: a writer killed mid-chunk
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:cut_at])
    rc, got = _info(cut, capsys)
    assert rc == 1 and not got["complete"] and got["damage"] == []
    assert f"cut off at byte {chunks[2][0]} of {cut_at}" in got["truncated_at"]
    assert main(["log", "info", str(cut)]) == 1
    assert "TRUNCATED" in capsys.readouterr().out
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(cut), str(fixed)]) == 0  # what a killed writer loses: nothing else
    assert "cut off at byte" in capsys.readouterr().out
    assert _info(fixed, capsys)[1]["messages"] == got["messages"]
    assert main(["replay", str(cut)]) == 0  # the ticks before the cut replay
    assert "identical" in capsys.readouterr().out
