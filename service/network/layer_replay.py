"""Replay of a coordinator's log (energyctl coordinator --out): the layer rebuilt from the scenario in the log,
fed what the coordinator saw each sample, must give every allocation it recorded (P^{r,in} and its rate as every
source forms them from the grid sample, the v_ref it held) bit for bit, and each plug-in verdict it gave.
Pure apart from reading the file: no clock, no socket."""

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


def replay_coordinator(path: str | Path, impl: str = "auto") -> dict:
    """{"identical", "samples", "allocations", "mismatches" (the first few), "verdicts", "verdicts_differing",
    "offers", "offers_differing" (each plug-in offer recomputed at the sample it was made before), "gaps"}: gaps
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
           "verdicts_differing": [], "offers": 0, "offers_differing": [], "gaps": 0}
    prev = None
    verdict_seqs = sorted(connects)
    hs = Handshakes(layer, names, with_offers=any(e["kind"] == "offer" for e in events))
    vi = 0
    for tk in ticks:
        k = tk["seq"]
        if prev is not None and k != prev + 1:
            out["gaps"] += 1
            if k == 0:  # the rig restarted: the coordinator started a new layer
                layer = hs.layer = InterconnectionLayer(net, loads)
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
        v_ref_sent = list(layer.v_ref)
        want, rate = layer.allocate(k, P, connected)
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
        layer.step(k, (v, i_out, connected, [tk["bus_v_mean"]] if tk["has_buses"] else [], [tk["load_W"]]),
                   [True] * len(names), list(connected))
    out["identical"] = (out["n_mismatches"] == 0 and not out["verdicts_differing"] and not out["offers_differing"]
                        and out["samples"] > 0)
    return out
