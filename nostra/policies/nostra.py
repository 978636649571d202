"""BC-NOSTRA: one stochastic latent per modality, so any subset can be imagined (MLI / AdaMLI)."""

from nostra.policies.state_space import StateSpaceNet, StateSpaceRunner


class NostraNet(StateSpaceNet):
    policy = "nostra"
    joint_latent = False


class NostraRunner(StateSpaceRunner):
    policy = "nostra"
