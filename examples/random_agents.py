"""Random agents on the synthetic city: the whole ParallelEnv loop in ten lines."""

import marl_amod

env = marl_amod.parallel_env("synthetic", reward_mode="team")
observations, infos = env.reset(seed=0)
total = 0.0
while env.agents:
    actions = {agent: env.action_space(agent).sample() for agent in env.agents}
    observations, rewards, terminations, truncations, infos = env.step(actions)
    total += rewards["region_0"]  # team reward: the same for every agent
print(f"episode profit {total:.1f}, served {infos['region_0']['system_served_demand']:.0f} requests")
