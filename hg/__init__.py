"""haptic-glance: reinforcement-learned tactile probing for 3D object recognition.

Importing `hg` registers the gymnasium environment `HapticGlance-v0` (as `import panda_gym` does its own), so
`gymnasium.make("HapticGlance-v0")` works after `import hg`, and `gymnasium.make("hg:HapticGlance-v0")` without.
The entry points are strings: the simulator is imported only when an environment is made.
"""
import gymnasium

gymnasium.register("HapticGlance-v0", entry_point="hg.sim.gym_env:HapticGlanceEnv",
                   vector_entry_point="hg.sim.gym_env:HapticGlanceVectorEnv", max_episode_steps=None)
