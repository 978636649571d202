"""Building blocks of the policies: encoders, the multimodal state-space core, fusion, action heads."""
