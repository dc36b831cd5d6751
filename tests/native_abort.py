"""A gymnasium wrapper that ends its process as a native crash in a simulator would (``os.abort``,
SIGABRT) at the first step, for the tests of the env check before a run: a real process that dies,
never an exception."""
import os

import gymnasium as gym


class AbortAtStep(gym.Wrapper):
    def step(self, action):
        os.abort()
