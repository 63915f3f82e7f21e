"""Cao et al. (SuctionNet-1Billion baseline): an RGB-D fully convolutional net predicting a seal heatmap
and an object-centre heatmap; their product ranks suction candidates.

- ``config``: CaoConfig, every knob; stored in each checkpoint.
- ``targets``: dense seal / centre training maps from a labelled dataset scene.
- ``network``: the light U-Net and its input normalisation.
- ``train``: ``python -m policies.cao.train --data DIR --out policies/cao/checkpoint.pt``.
- ``policy``: CaoPolicy (registry name ``cao``).
"""
