"""Loop closure through reinforcement learning (dissertation Ch. 3, SPEC 6.9).

Importing the package registers the grid world as ``objslam/LoopClosureGrid-v0``.
"""

import gymnasium

ENV_ID = "objslam/LoopClosureGrid-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="rl.env:LoopClosureGrid")
