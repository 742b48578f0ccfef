"""The learning agents: one DQN core and the paper's four methods. They see arrays, masks and rewards
only: no simulator, no highway-env.
"""
