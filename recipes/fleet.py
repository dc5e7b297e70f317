"""Multi-agent learners on a fleet of vehicles (MODEL.md § C), scored against the centralised optimum.

python recipes/fleet.py                                      # VDN, 2 vehicles, own observations
python recipes/fleet.py learner=joint env.observe=full       # one network over the joint actions
python recipes/fleet.py learner=qmix env.share=1.0 env.channels=2
python recipes/fleet.py learner=idqn env.vehicles=4          # beyond the exact model: Monte-Carlo
"""

from irdrc.recipes.fleet import recipe
from irdrc.runs import app

if __name__ == "__main__":
    app.main(recipe)
