"""AML: amortized maximum likelihood shape completion (Stutz & Geiger, ``shared/papers/aml.txt``).

Two steps, as in the paper (Fig. 2):

1. **Shape prior** (Eq. 1-3). A 3D-conv VAE on reference shapes: SynthCars' complete
   canonical car surfaces voxelised to occupancy + SDF grids (``geometry/voxels.py``), two
   channels, 24 x 54 x 24 (H x L x W). Recognition model ``q(z|y) = N(mu(y), diag sigma^2(y))``,
   ``Q = 10``; generative model ``p(y_i|z)``: Bernoulli occupancy (sigmoid logits) and
   Gaussian SDF with ``log sigma^2 = -2``. Loss: BCE + Gaussian NLL + KL, one sample per step,
   light rotation / scale / translation augmentation of the grids.
2. **Amortized ML** (Eq. 5). The decoder is frozen; a new deterministic encoder ``z(x; w)``
   maps an *observation* (occupied / ray-cast free / unknown voxels of a partial scan) to a
   latent code, trained on partial observations only with the negative log-likelihood of the
   observed voxels (occupied = 1, free = 0) plus ``lambda * ||z||^2 / 2``. For the SDF
   channel the observation's likelihood is ``P(sdf <= 0) = Phi(-mu / sigma)`` (the paper's
   reparameterisation), so both channels give a cross-entropy. ``lambda`` is chosen on a
   validation split by the ML baseline (below) and recorded in the checkpoint.

**ML baseline** (Eq. 4): the same objective minimised per instance over ``z`` by Adam from
the prior mean, batched over instances (backend ``aml_ml``, same weights). ``aml`` can refine
its encoder's codes by a few such steps (``refine_steps``, ``refine_lr``).

Output: marching cubes (scikit-image) on the decoded SDF of the whole batch in one call, a
triangle mesh per instance, ``output_points`` points sampled uniformly by area on it (seeded
by the input cloud's content), in the canonical frame.

Architecture (paper: three stages of two conv + BN + ReLU with max-pool / nearest
upsampling). For the CPU budget (<= 5 ms per car at batch 32 with marching cubes) the stages
run at half resolution: the encoders start with a 2 x 2 x 2 space-to-depth of the grid
(12 x 27 x 12 x 8C) and the decoder ends with the inverse depth-to-space of a 1 x 1 x 1
convolution, so no 3 x 3 x 3 convolution touches the 31k-voxel full-resolution grid.

The package, one concern per module (this ``__init__`` re-exports their public names and,
by importing :mod:`.recipe`, attaches the training recipe to the ``aml`` backend):

* :mod:`.network`: presets, grids, the VAE and the observation encoder (``AMLNet``);
* :mod:`.likelihood`: the observed-voxel and reference negative log-likelihoods;
* :mod:`.surface`: batched marching cubes and area-uniform sampling of the meshes;
* :mod:`.completer`: the registered backends ``aml`` and ``aml_ml``;
* :mod:`.prior`: the reference shapes, augmentation, VAE loss, validation, latent whitening;
* :mod:`.lambda_selection`: lambda (by the ML baseline) and the refinement chosen on validation data;
* :mod:`.recipe`: ``pcc train aml --stage prior|encoder``.
"""

from __future__ import annotations

from pcc_ros.models.aml.completer import (
    AML,
    AMLMaximumLikelihood,
    box_aspects,
    canonical_origins,
)
from pcc_ros.models.aml.lambda_selection import (
    Codes,
    RealCrops,
    holdout_fidelity,
    ml_codes,
    real_crops,
    refined_codes,
    select_lambda,
    select_refinement,
)
from pcc_ros.models.aml.likelihood import (
    observed_nll,
    reference_nll,
)
from pcc_ros.models.aml.network import (
    DEFAULT_ASPECT,
    GRIDS,
    PRESETS,
    AMLNet,
    Decoder,
    Encoder,
    depth_to_space,
    grid_of,
    space_to_depth,
)
from pcc_ros.models.aml.prior import (
    PriorBatch,
    ReferenceSet,
    augment_grids,
    hash_split,
    shape_to_grid_frame,
    synthcars_reference_shapes,
    vae_loss,
    validate_prior,
    whiten_latent,
)
from pcc_ros.models.aml.recipe import (
    AMLRecipe,
    ObservationBatch,
    Observations,
    training_recipe,
)
from pcc_ros.models.aml.surface import (
    marching_cubes_batch,
    sample_meshes,
    surface_samples,
)

__all__ = [
    "AML",
    "DEFAULT_ASPECT",
    "GRIDS",
    "PRESETS",
    "AMLMaximumLikelihood",
    "AMLNet",
    "AMLRecipe",
    "Codes",
    "Decoder",
    "Encoder",
    "ObservationBatch",
    "Observations",
    "PriorBatch",
    "RealCrops",
    "ReferenceSet",
    "augment_grids",
    "box_aspects",
    "canonical_origins",
    "depth_to_space",
    "grid_of",
    "hash_split",
    "holdout_fidelity",
    "marching_cubes_batch",
    "ml_codes",
    "observed_nll",
    "real_crops",
    "reference_nll",
    "refined_codes",
    "sample_meshes",
    "select_lambda",
    "select_refinement",
    "shape_to_grid_frame",
    "space_to_depth",
    "surface_samples",
    "synthcars_reference_shapes",
    "training_recipe",
    "vae_loss",
    "validate_prior",
    "whiten_latent",
]
