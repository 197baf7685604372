"""One PPO policy shared by every region (parameter sharing) with SuperSuit and Stable-Baselines3.

SuperSuit turns the N agents of the ParallelEnv into N rows of a vector env, so one SB3 policy
acts for every region. ``ConcatVecEnv`` lacks ``seed`` (SB3 calls it), so a small wrapper forwards
the seed to the vector env's reset.

    pip install "marl-amod[sb3]"
    python examples/sb3_parameter_sharing.py --steps 20000
"""

from __future__ import annotations

import argparse

import supersuit as ss
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnvWrapper

import marl_amod


class SeedForwarding(VecEnvWrapper):
    """Keeps the seed SB3 gives and passes it to the ConcatVecEnv's reset."""

    def __init__(self, venv):
        super().__init__(venv)
        self._seed = None

    def seed(self, seed=None):
        self._seed = seed
        return [seed]

    def reset(self):
        seed, self._seed = self._seed, None
        if seed is None:
            return self.venv.reset()
        obs, self.venv.reset_infos = self.venv.venv.reset(seed=seed)
        return obs

    def step_wait(self):
        return self.venv.step_wait()


def make_vec_env(scenario: str, copies: int):
    env = marl_amod.parallel_env(scenario)
    vec = ss.pettingzoo_env_to_vec_env_v1(env)  # one row per region
    vec = ss.concat_vec_envs_v1(vec, copies, num_cpus=0, base_class="stable_baselines3")
    return SeedForwarding(vec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=20_000, help="agent-steps to train")
    parser.add_argument("--copies", type=int, default=2, help="env copies side by side")
    args = parser.parse_args()
    vec = make_vec_env(args.scenario, args.copies)
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
