"""The tick index: one row of doubles per daemon tick (its meas, z_in and cmd fields), written beside the JSON
channels as zstd-compressed MCAP attachments, so replay reads a long log without parsing a message."""

from __future__ import annotations

from array import array


class TickIndex:
    """Replay index written beside the JSON channels: per tick, the measurement, what else the core was given and
    its answer, as one row of doubles (``COLUMNS``), flushed every ``every`` ticks as a zstd-compressed MCAP
    attachment. Foxglove reads the JSON channels; replay reads these rows and skips decompressing and parsing
    the JSON (it uses them only when their count equals the file's meas and z_in counts: same ticks, same
    doubles, since both are written from the same ring slots)."""

    NAME = "energyctl.ticks"
    MEDIA_TYPE = "application/x-energyctl-ticks+zstd"
    COLUMNS = ("seq", "t", "i", "v", "u", "i_load", "P_r_in", "P_r_in_dot", "stepped", "du_dt", "du_dt_next")

    def __init__(self, k_meas: int, k_zin: int, k_cmd: int, every: int = 8192):
        self.kinds = (k_meas, k_zin, k_cmd)
        self.every = every
        self.rows = array("d")
        self._m: tuple | None = None
        self._z: tuple | None = None

    @classmethod
    def for_topics(cls, topics: list[str], magics: list[int]) -> TickIndex | None:
        """The index for a daemon's stream set (meas, z_in and cmd with the wire codecs), else None."""
        from schemas.codec import CMD, MEAS, TICK_IN

        want = {("meas", MEAS.magic), ("z_in", TICK_IN.magic), ("cmd", CMD.magic)}
        found = {(t.rsplit("/", 1)[-1], m): k for k, (t, m) in enumerate(zip(topics, magics, strict=True))}
        if not want <= set(found):
            return None
        return cls(found["meas", MEAS.magic], found["z_in", TICK_IN.magic], found["cmd", CMD.magic])

    def metadata(self) -> dict[str, str]:
        return {"attachment": self.NAME, "media_type": self.MEDIA_TYPE, "columns": ",".join(self.COLUMNS),
                "dtype": "<f8"}

    def take(self, k: int, vals: tuple) -> bool:
        """One message of the three streams; True when a flush is due."""
        km, kz, _ = self.kinds
        if k == km:
            self._m = vals
        elif k == kz:
            self._z = vals
        else:
            m, z = self._m, self._z
            if m is not None and z is not None and m[0] == z[0] == vals[0]:
                self.rows.extend((m[0], m[1], m[2], m[3], m[4], m[5], z[2], z[3], z[4], vals[2], vals[3]))
            self._m = self._z = None
            return len(self.rows) >= self.every * len(self.COLUMNS)
        return False

    def flush(self, f) -> None:
        if not self.rows:
            return
        import zstandard

        f.attachment(self.NAME, self.MEDIA_TYPE, zstandard.ZstdCompressor(level=1).compress(self.rows.tobytes()),
                     self.rows[1])
        self.rows = array("d")
