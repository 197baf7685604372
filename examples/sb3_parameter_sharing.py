"""One PPO policy shared by every region (parameter sharing) with SuperSuit and Stable-Baselines3.

SuperSuit turns the N agents of the ParallelEnv into N rows of a vector env, so one SB3 policy
acts for every region; ``marl_amod.integrations.sb3.sb3_vec_env`` does that and forwards SB3's
seed, which SuperSuit's vector env would drop.

    pip install "marl-amod[sb3]"
    python examples/sb3_parameter_sharing.py --steps 20000
"""

from __future__ import annotations

import argparse

from stable_baselines3 import PPO

import marl_amod
from marl_amod.integrations.sb3 import sb3_vec_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=20_000, help="agent-steps to train")
    parser.add_argument("--copies", type=int, default=2, help="env copies side by side")
    args = parser.parse_args()
    vec = sb3_vec_env(marl_amod.parallel_env(args.scenario), copies=args.copies)
    model = PPO("MlpPolicy", vec, n_steps=64, batch_size=256, seed=0, verbose=1)
    model.learn(total_timesteps=args.steps)

    env = marl_amod.parallel_env(args.scenario)
    obs, _ = env.reset(seed=123)
    while env.agents:
        actions = {a: model.predict(obs[a], deterministic=True)[0] for a in env.agents}
        obs, rewards, _, _, infos = env.step(actions)
    print(f"evaluation profit {infos['region_0']['system_profit']:.1f}")


if __name__ == "__main__":
    main()
