"""Replay of a coordinator's log (energyctl coordinator --out): the layer rebuilt from the scenario in the log,
fed what the coordinator saw each sample, must give every allocation it recorded (P^{r,in} and its rate as every
source forms them from the grid sample, the v_ref it held) bit for bit, every LayerWindow message it sent (topics
``<prefix>/<id>/window/<source>``: alpha_s, v_ref, breaker, Z^{r,in}, window, seq) field for field, and each plug-in
verdict it gave. Pure apart from reading the file: no clock, no socket."""

from __future__ import annotations

import json
from pathlib import Path

from schemas.network import NetworkScenario
from schemas.scenario import ControllerConfig
from service.logio.reader import LogError, messages, scan
from service.network.layer import STALE_OFFER, InterconnectionLayer, judge_announced, offer_staleness
from service.plant.network import LoadForecast


def is_coordinator_log(path: str | Path) -> bool:
    return "coordinator" in scan(path)["metadata"]


class Handshakes:
    """The coordinator's plug-in offers and its verdicts on announced Z^{r,out}, recomputed from the replayed layer
    (``layer``, replaced by the caller when the rig restarts). It keeps the offers per source as the coordinator does
    (an announcement uses up its source's offer), so a refusal for a stale offer is recomputed too. A log without offer
    events (an older coordinator's) judges each announcement on the offer logged with it."""

    def __init__(self, layer: InterconnectionLayer, names: list[str], with_offers: bool = True):
        self.layer, self.names, self.with_offers = layer, names, with_offers
        self.kept: dict[str, tuple[int, tuple]] = {}  # source -> (window, breakers) of its offer

    def offer(self, d: dict) -> tuple[list, list] | None:
        """A logged offer event's detail: None if the layer gives it again bit for bit, else (logged, replayed)."""
        s = self.names.index(d["source"])
        box, tau_p = self.layer.connect_offer(s, d["window"], d["connected"])
        got = [list(box), tau_p, self.layer.v_ref[s]]
        self.kept[d["source"]] = (d["window"], tuple(d["connected"]))
        logged = [d["box"], d["tau_prime_s"], d["v_ref_V"]]
        return None if got == logged else (logged, got)

    def announced(self, d: dict, seq: int) -> str:
        """A logged verdict on an announcement (logged at sample seq): the reason the coordinator's rules give."""
        if self.with_offers:
            stale = offer_staleness(self.kept.pop(d["source"], None), seq // self.layer.per_window, d["connected"])
            if stale:
                return stale
        elif d["reason"].startswith(STALE_OFFER):
            return d["reason"]
        return judge_announced(tuple(d["offer"]["box"]), d["offer"]["tau_prime_s"], tuple(d["Z_out"]["P"]),
                               tuple(d["Z_out"]["Qdot"]), d.get("saturation", ""))[0]


WINDOW_FIELDS = ("seq", "t", "window", "alpha", "v_ref_V", "connected", "has_range", "Z_P_min", "Z_P_max",
                 "Z_Qdot_min", "Z_Qdot_max")  # a LayerWindow's fields, in its wire order (schemas.codec.WINDOW)
_NO_RANGE = (0.0, 0.0, 0.0, 0.0)


def window_messages(layer: InterconnectionLayer, seq: int, t: float, window: int, zin: list, connected: list[bool]
                    ) -> list[tuple]:
    """Each source's LayerWindow as the coordinator's _send_window forms it (values in WINDOW_FIELDS order): from
    sample seq on, for window, alpha_s = layer.sharing.alpha(connected), the v_ref the layer holds, Z^{r,in} = zin[j]
    (None: no range, zeros)."""
    alpha = layer.sharing.alpha(connected)
    return [(seq, t, window, alpha[j], layer.v_ref[j], bool(connected[j]), zin[j] is not None,
             *(zin[j] if zin[j] is not None else _NO_RANGE)) for j in range(len(connected))]


def compare_windows(logged: dict[str, list[dict]], replayed: dict[str, list[tuple]]) -> tuple[int, int, list[dict]]:
    """(windows logged, how many differ, the first 5 that do): per source, the logged LayerWindow messages against
    the replayed ones (WINDOW_FIELDS order), matched by seq and then by their order at that seq (a breaker change and
    a window's end may both send one for the same seq), every field compared with ==. A replayed message with no
    logged one, or a logged one with none replayed, differs too."""
    n, n_diff, first = 0, 0, []
    for name in sorted(set(logged) | set(replayed)):
        by_seq: dict[int, list[list]] = {}
        for m in logged.get(name, []):
            by_seq.setdefault(m["seq"], [[], []])[0].append(tuple(m[f] for f in WINDOW_FIELDS))
        for m in replayed.get(name, []):
            by_seq.setdefault(m[0], [[], []])[1].append(tuple(m))
        n += len(logged.get(name, []))
        for seq in sorted(by_seq):
            lg, rp = by_seq[seq]
            for i in range(max(len(lg), len(rp))):
                a = lg[i] if i < len(lg) else None
                b = rp[i] if i < len(rp) else None
                if a != b:
                    n_diff += 1
                    if len(first) < 5:
                        fields = ([f for f, x, y in zip(WINDOW_FIELDS, a, b, strict=True) if x != y]
                                  if a is not None and b is not None else list(WINDOW_FIELDS))
                        first.append({"seq": seq, "source": name, "fields": fields,
                                      "logged": None if a is None else dict(zip(WINDOW_FIELDS, a, strict=True)),
                                      "replayed": None if b is None else dict(zip(WINDOW_FIELDS, b, strict=True))})
    return n, n_diff, first


def replay_coordinator(path: str | Path, impl: str = "auto") -> dict:
    """{"identical", "samples", "allocations", "mismatches" (the first few), "windows", "windows_differing" (the
    first 5), "n_windows_differing", "verdicts", "verdicts_differing", "offers", "offers_differing" (each plug-in
    offer recomputed at the sample it was made before), "gaps", "notes"}: windows are the LayerWindow messages the
    coordinator logged as sent (a log without them, an older coordinator's, has 0 and a note), each recomputed as
    the coordinator forms it (compare_windows); gaps
    count the samples the coordinator did not answer (a realtime coordinator answers the newest; the layer is fed
    what it answered, as live) and a rig's restarts."""
    meta = scan(path)["metadata"]
    if "coordinator" not in meta or "scenario" not in meta:
        raise LogError(f"{path}: not a coordinator log (no 'coordinator' and 'scenario' metadata)")
    net = NetworkScenario.model_validate_json(meta["scenario"]["json"])
    cfg = json.loads(meta["coordinator"]["json"])
    base = f"{cfg['prefix']}/{cfg['id']}"
    names = list(net.sources)
    ticks = messages(path, f"{base}/layer/tick")
    per = {n: {d["seq"]: d for d in messages(path, f"{base}/layer/{n}")} for n in names}
    events = messages(path, f"{base}/events")
    logged_windows = {n: messages(path, f"{base}/window/{n}") for n in names}
    loads = LoadForecast(net)
    layer = InterconnectionLayer(net, loads)
    for e in events:
        if e["kind"] == "resume":
            for n, v in json.loads(e["detail"])["v_ref_V"].items():
                layer.v_ref[names.index(n)] = v
    connects = {}  # seq -> [(kind, detail)]: the offers and plug-in verdicts answered before that sample
    for e in events:
        if e["kind"] in ("connect", "offer"):
            connects.setdefault(e["seq"], []).append((e["kind"], json.loads(e["detail"])))
    out = {"samples": 0, "allocations": 0, "mismatches": [], "n_mismatches": 0, "verdicts": 0,
           "verdicts_differing": [], "offers": 0, "offers_differing": [], "gaps": 0, "notes": []}
    prev = None
    # the coordinator's window state (Coordinator.grid): the breakers it last saw, the window and Z^{r,in} it holds
    seen, first, window, zin = [s.connected for s in net.sources.values()], True, 0, [None] * len(names)
    sent: dict[str, list[tuple]] = {n: [] for n in names}

    def send(seq: int, t: float, connected: list[bool]) -> None:
        for n, m in zip(names, window_messages(layer, seq, t, window, zin, connected), strict=True):
            sent[n].append(m)

    verdict_seqs = sorted(connects)
    hs = Handshakes(layer, names, with_offers=any(e["kind"] == "offer" for e in events))
    vi = 0
    for tk in ticks:
        k = tk["seq"]
        if prev is not None and k != prev + 1:
            out["gaps"] += 1
            if k == 0:  # the rig restarted: the coordinator started a new layer
                layer = hs.layer = InterconnectionLayer(net, loads)
                first = True
        prev = k
        # plug-in verdicts answered before this sample (after the previous one), with the layer's state then
        while vi < len(verdict_seqs) and verdict_seqs[vi] <= k:
            for kind, d in connects[verdict_seqs[vi]]:
                if kind == "offer":  # what the source was offered, recomputed from the layer's state then
                    out["offers"] += 1
                    diff = hs.offer(d)
                    if diff is not None:
                        out["offers_differing"].append({"seq": verdict_seqs[vi], "source": d["source"],
                                                        "logged": diff[0], "replayed": diff[1]})
                    continue
                if "controller" not in d or d.get("reason") == "already connected" or d.get("checked") is False:
                    continue
                s = names.index(d["source"])
                if d.get("announced"):  # the source's own forecast, judged against the offer it was made for
                    reason = hs.announced(d, verdict_seqs[vi])
                else:
                    f = layer.connect_check(s, ControllerConfig.model_validate(d["controller"]), d["window"],
                                            d["connected"], net.timing.delay_samples, impl)
                    reason = f.reason
                feasible = reason == ""
                out["verdicts"] += 1
                rig_refused = not d["accepted"] and d["reason"].startswith("the rig")
                if (feasible != d["accepted"] and not rig_refused) or (not feasible and reason != d["reason"]):
                    out["verdicts_differing"].append({"seq": verdict_seqs[vi], "source": d["source"],
                                                      "logged": [d["accepted"], d["reason"]],
                                                      "replayed": [feasible, reason]})
            vi += 1
        rows = [per[n].get(k) for n in names]
        if any(r is None for r in rows):
            out["gaps"] += 1
            continue
        out["samples"] += 1
        v = [r["v"] for r in rows]
        i_out = [r["i_out"] for r in rows]
        connected = [bool(r["connected"]) for r in rows]
        P = [v[j] * i_out[j] if connected[j] else 0.0 for j in range(len(names))]
        topology = connected != seen or first
        seen, first = connected, False
        if topology and layer.active:
            window = k // layer.per_window
            zin = layer.ranges(window, connected)
        v_ref_sent = list(layer.v_ref)
        want, rate = layer.allocate(k, P, connected)
        if topology:
            send(k, tk["t"], connected)
        for j, n in enumerate(names):
            r = rows[j]
            out["allocations"] += 1
            got = (want[j], rate[j], v_ref_sent[j])
            logged = (r["P_r_in"], r["P_r_in_dot"], r["v_ref_V"])
            if got != logged:
                out["n_mismatches"] += 1
                if len(out["mismatches"]) < 5:
                    out["mismatches"].append({"seq": k, "source": n, "logged": logged, "replayed": got})
        # as the coordinator: active = connected
        win_k, _ = layer.step(k, (v, i_out, connected, [tk["bus_v_mean"]] if tk["has_buses"] else [],
                                  [tk["load_W"]]), [True] * len(names), list(connected))
        if win_k is not None:  # the next window's message, before its first sample
            window = win_k
            if layer.active:
                zin = layer.ranges(win_k, connected)
            send(k + 1, tk["t"], connected)
    if any(logged_windows.values()):
        out["windows"], out["n_windows_differing"], out["windows_differing"] = compare_windows(logged_windows, sent)
    else:
        out["windows"], out["n_windows_differing"], out["windows_differing"] = 0, 0, []
        out["notes"].append("no window messages in this log (a coordinator before they were recorded): the "
                            "LayerWindow messages it sent are not compared")
    out["identical"] = (out["n_mismatches"] == 0 and not out["verdicts_differing"] and not out["offers_differing"]
                        and out["n_windows_differing"] == 0 and out["samples"] > 0)
    return out
