"""BC-RSSM: the same core with one joint latent over all modalities; latent imagination (LI)
replaces the whole latent by its prior whenever any modality is imagined."""

from nostra.policies.state_space import StateSpaceNet, StateSpaceRunner


class RSSMNet(StateSpaceNet):
    policy = "rssm"
    joint_latent = True


class RSSMRunner(StateSpaceRunner):
    policy = "rssm"
