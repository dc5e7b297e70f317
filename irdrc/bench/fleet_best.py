"""The best decentralised policy of each cell of ``recipes/bench_fleet.py`` (N = 2, own
observations), and the two gaps it separates: **information** — the centralised optimum against the
best decentralised policy found (what a vehicle cannot do without the other's state) — and
**learning** — each learner against that policy (what training leaves on the table).

The search (``irdrc.fleet.search.best_decentralised``) starts from every own-observation run of the
cell, from the baselines' tables and from structured and random tables, improves each by first-order
steps on the exact model, and certifies the best by exact single switches: a local optimum of the
decentralised policies, not a proof of the global one (the policy space is 2^(2·352)).
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

import torch

from irdrc.runs.results import atomic_write_text, md_table, write_rows_csv

RANDOM_STARTS = 2
"""Random tables among each cell's starts (seeded by the start's index)."""


def run_tables(model: Any, policy_csv: Path) -> torch.Tensor:
    """[N, S] each vehicle's own table from a fleet run's ``policy.csv`` (a joint action per joint
    state, ``action1`` … ``actionN``): with own observations each vehicle's action depends on its
    own state alone, so any joint state carrying it gives it."""
    lines = Path(policy_csv).read_text().splitlines()
    header = lines[0].split(",")
    cols = [header.index(f"action{i + 1}") for i in range(model.N)]
    joint = torch.tensor([[int(x.split(",")[c]) for c in cols] for x in lines[1:]])
    states = model.vehicle_states()
    tables = torch.zeros(model.N, model.single.num_states, dtype=torch.int64)
    for i in range(model.N):
        tables[i, states[:, i]] = joint[:, i]
    return tables


def structured_starts(model: Any) -> list[tuple[str, torch.Tensor]]:
    """Starts that need no learner: the copies of each vehicle's single optimum, radar and comm
    always, one vehicle watching the road while the other runs its single optimum (each way), and
    ``RANDOM_STARTS`` random tables."""
    from irdrc.fleet.policies import single_optima

    S, N = model.single.num_states, model.N
    single = single_optima(model)
    radar, comm = torch.ones(S, dtype=torch.int64), torch.zeros(S, dtype=torch.int64)
    out = [
        ("copies of the single optimum", single),
        ("radar always", radar.expand(N, S).clone()),
        ("comm always", comm.expand(N, S).clone()),
    ]
    for i in range(N):
        roles = single.clone()
        roles[i] = radar
        out.append((f"vehicle {i + 1} radar always, the others their single optimum", roles))
    for k in range(RANDOM_STARTS):
        g = torch.Generator().manual_seed(k)
        out.append((f"random {k}", torch.randint(0, 2, (N, S), generator=g)))
    return out


def best_per_cell(
    rows: list[dict[str, Any]], specs: dict[str, Any], out: Path, sweeps: int
) -> tuple[str, list[dict[str, Any]]]:
    """For every cell of ``rows`` (part A's runs, ``specs`` their fleets by point id): the best
    decentralised policy found, written to ``best_decentralised.csv`` (a row per cell, vehicle and
    state); returns the Markdown section and one summary row per cell. A cell's finished search is
    kept in ``search/`` and reused by a later run of the same directory with the same starts."""
    from irdrc.fleet.model import FleetModel
    from irdrc.fleet.search import best_decentralised, improve_tables

    cells = sorted({(r["share"], r["channels"]) for r in rows})
    found, tables_out, text = [], [], []
    for share, k in cells:
        mine = [r for r in rows if (r["share"], r["channels"]) == (share, k)]
        own = [r for r in mine if r["observe"] == "own"]
        if not own:
            continue
        model = FleetModel(specs[own[0]["point_id"]])
        opt = own[0]["avg_reward"] / own[0]["final_ratio"]
        starts = [
            (f"{r['learner']} seed {r['seed']}", run_tables(model, _policy(out, r))) for r in own
        ] + structured_starts(model)
        print(f"\nbest decentralised policy, share {share:g}, {k} channel(s): {len(starts)} starts")

        def say(name: str, res: Any, opt: float = opt) -> None:
            print(f"  {name}: {res.start_reward / opt:.4f} → {res.reward / opt:.4f}", flush=True)

        key = {"starts": [name for name, _ in starts], "sweeps": sweeps, "centralised": opt}
        cell = _cached(out, share, k, key)
        if cell is None:
            best = best_decentralised(model, starts, certify=False, progress=say)
            cert = improve_tables(model, best.tables, max_sweeps=sweeps)
            say(f"{best.start}, every single switch", cert)
            cell = {
                "start": best.start,
                "reward": cert.reward,
                "sweeps_run": cert.sweeps,
                "flips": cert.flips,
                "tables": cert.tables.tolist(),
            }
            atomic_write_text(_cache_path(out, share, k), json.dumps({"key": key, "cell": cell}))
        else:
            print(f"  (found by an earlier run: {_cache_path(out, share, k)})")
        tables = torch.tensor(cell["tables"], dtype=torch.int64)
        ratio = cell["reward"] / opt
        learners = {}
        for learner in dict.fromkeys(r["learner"] for r in own):
            learners[learner] = statistics.median(
                r["final_ratio"] for r in own if r["learner"] == learner
            )
        found.append(
            {
                "share": share,
                "channels": k,
                "centralised": opt,
                "best_decentralised": cell["reward"],
                "best_ratio": ratio,
                "best_start": cell["start"],
                "starts": len(starts),
                "certify_sweeps": cell["sweeps_run"],
                "certify_flips": cell["flips"],
                "local_optimum": cell["flips"] == 0 or cell["sweeps_run"] < sweeps,
                **{f"{name}_ratio": v for name, v in learners.items()},
            }
        )
        S = model.single.num_states
        for i in range(model.N):
            tables_out += [
                {"share": share, "channels": k, "vehicle": i + 1, "state": s, "action": int(a)}
                for s, a in zip(range(S), tables[i].tolist(), strict=True)
            ]
        learned = ", ".join(
            f"{name} {v:.4f} (gap {1 - v / ratio:+.4f})" for name, v in learners.items()
        )
        text.append(
            [
                f"{share:g}",
                str(k),
                f"**{ratio:.4f}**",
                f"{1 - ratio:.4f}",
                cell["start"],
                learned,
            ]
        )
    write_rows_csv(out / "best_decentralised.csv", tables_out)
    section = (
        "**The best decentralised policy found and the two gaps** (N = 2, own observations; "
        "ratios of the exact centralised optimum; learners: median final ratio over the seeds, "
        "and its learning gap 1 − learner / best found)\n\n"
        + md_table(
            [
                "share",
                "channels",
                "best decentralised found",
                "information gap (1 − best)",
                "found from",
                "learners (learning gap)",
            ],
            text,
        )
        + "\n\nEach cell's search starts from every own-observation run, the baselines' tables, "
        f"both role splits and {RANDOM_STARTS} random tables, improves each on the exact model "
        "(`irdrc.fleet.search`) and certifies the best by exact single switches "
        "(`best_decentralised.csv` has its tables; a resumed run reuses a cell whose search "
        "finished with the same starts, `search/`)."
    )
    return section, found


def _policy(out: Path, row: dict[str, Any]) -> Path:
    return Path(out) / "trials" / row["point_id"] / "policy.csv"


def _cache_path(out: Path, share: float, channels: int) -> Path:
    path = Path(out) / "search" / f"share{share:g}_channels{channels}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _cached(out: Path, share: float, channels: int, key: dict[str, Any]) -> dict[str, Any] | None:
    """A cell's finished search from an earlier run of the same directory, if its starts, sweeps
    and centralised optimum are the same (a resumed benchmark skips it); else None."""
    path = _cache_path(out, share, channels)
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    same = saved["key"]["starts"] == key["starts"] and saved["key"]["sweeps"] == key["sweeps"]
    return (
        saved["cell"]
        if same and abs(saved["key"]["centralised"] - key["centralised"]) < 1e-9
        else None
    )
