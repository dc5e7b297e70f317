"""The paper's Figure 2 and its claims, regenerated against the exact optimum.

    python recipes/figure2.py                                     # the default run (docs/REPRODUCTION.md)
    python recipes/figure2.py seeds=[0,1,2] p1_speed=[0.1,0.5,1.0] methods=[dqn,qlearning]
    python recipes/figure2.py "learners.dqn_paper.overrides=['algo=dqn_paper','algo.total_frames=200000']"
    python recipes/figure2.py executor=local                      # without Ray, one run after another
    python recipes/figure2.py resume=true hydra.run.dir=outputs/figure2   # finish an interrupted run

Training runs go through the sweep engine (Ray Tune by default); on machines without outside
network start it inside a loopback-only namespace: ``unshare -n sh -c 'ip link set lo up; …'``.
"""

from irdrc.paper import figure2
from irdrc.runs import app

if __name__ == "__main__":
    app.main(figure2)
