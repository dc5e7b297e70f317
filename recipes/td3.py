"""TD3 on the radar share of each step (MODEL.md § D), scored exactly against the optimum over ρ.

python recipes/td3.py                                      # the paper scenario
python recipes/td3.py env.p1.speed=1.0 seed=3
"""

from irdrc.experiments import app, td3

if __name__ == "__main__":
    app.main(td3)
