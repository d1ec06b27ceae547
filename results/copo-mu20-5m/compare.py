"""CoPO ablation arms against the 5 M grid's CoPO and IPPO of one scene, same seeds 1–3,
same defaults and budget: training windows (MetaDrive's success) at 2 / 3 / 4 M and at the end,
the best window, crash and timeout at the end, μ at 2 M and at the end, the training agent
episode's mean length, then each arm minus IPPO and minus CoPO seed by seed.

    python3 results/copo-mu20-5m/compare.py "μ ≤ 20°=results/copo-mu20-5m/runs/mu20-s" \
        "meta step × 20/90=results/copo-metalr-5m/runs/metalr-s"

(run from the repository root; each argument is label=run-directory prefix before the seed;
a first argument scene=roundabout compares with the grid's roundabout runs instead).
"""
import importlib.util
import statistics as st
import sys
from pathlib import Path

# The interval arithmetic of the grid's tables (scripts/grid-tables.py), not a second copy.
_spec = importlib.util.spec_from_file_location(
    "grid_tables", Path(__file__).resolve().parents[2] / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)


def f(values, signed=False):
    return grid_tables.fmt(values, signed=signed)


def at(ps,m):
    q=[p for p in ps if p['agent_steps']<=m]; return q[-1]
arms=sys.argv[1:]  # label=dir/runs/prefix
scene='intersection'
if arms and arms[0].startswith('scene='):
    scene=arms.pop(0).split('=',1)[1]
grid='results/grid-5m/runs'
rows={}
print('| arm | 2 M | 3 M | 4 M | 5 M | best by 5 M | crash at 5 M | timeout at 5 M | μ at 2 M / 5 M | steps per agent |')
print('|---|---|---|---|---|---|---|---|---|---|')
for spec in arms+[f"CoPO (grid)={grid}/copo-{scene}-s", f"IPPO (grid)={grid}/ippo-{scene}-s"]:
    label,prefix=spec.split('=')
    ps=[grid_tables.read_progress(Path(f"{prefix}{s}")) for s in (1,2,3)]
    rows[label]=ps
    cells=[]
    for m in (2e6,3e6,4e6):
        cells.append(f([at(p,m)['scene_window']['success_rate'] for p in ps]))
    cells.append(f([p[-1]['scene_window']['success_rate'] for p in ps]))
    best=f([max(q['scene_window']['success_rate'] for q in p) for p in ps])
    last=[p[-1]['scene_window'] for p in ps]
    mu=", ".join(f"{p[-1]['lcf']['mean_deg']:.0f}°" for p in ps)
    mu2=", ".join(f"{at(p,2e6)['lcf']['mean_deg']:.0f}°" for p in ps)
    length=f"{st.mean(p[-1]['window']['mean_length'] for p in ps):.0f}"
    print(f"| {label} | "+" | ".join(cells)+f" | {best} | {f([w['crash_rate'] for w in last])} | {f([w['timeout_rate'] for w in last])} | {mu2} / {mu} | {length} |")
print()
base=rows["IPPO (grid)"]; copo=rows["CoPO (grid)"]
for label,ps in rows.items():
    if 'grid' in label: continue
    for name,b in (("IPPO",base),("CoPO",copo)):
        ds=[p[-1]['scene_window']['success_rate']-q[-1]['scene_window']['success_rate'] for p,q in zip(ps,b)]
        dc=[p[-1]['scene_window']['crash_rate']-q[-1]['scene_window']['crash_rate'] for p,q in zip(ps,b)]
        print(f"{label} − {name} at 5 M: success {f(ds,True)} ({', '.join(f'{d:+.2f}' for d in ds)}), crash {f(dc,True)} ({', '.join(f'{d:+.2f}' for d in dc)})")
