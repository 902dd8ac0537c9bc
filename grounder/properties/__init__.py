"""Learned physical properties: a prior over density, friction and contact for every grounded object.

- `prior`: the property model as `ground` uses it (load, predict per object, decode embeddings, sample variants).
- `network`: the torch network, its training recipe and evaluation (imported only when needed: torch is heavy).
- `training_data`: synthetic training data rendered with MuJoCo.
- `materials`: the material table (real-world ranges of density, friction and restitution).
- `model_files`: where the weights live (`weights/`), and the error a missing or broken model raises.

The names load on first use.
"""

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

_LAZY = {
    "WEIGHTS_DIR": "grounder.properties.model_files",
    "PropertyModelError": "grounder.properties.model_files",
    "PropertyModel": "grounder.properties.prior",
    "ObjectProperties": "grounder.properties.prior",
    "load_property_model": "grounder.properties.prior",
    "predict_properties": "grounder.properties.prior",
    "decode_embedding": "grounder.properties.prior",
    "sample_scene_variants": "grounder.properties.prior",
    "write_scene_variants": "grounder.properties.prior",
    "TrainOptions": "grounder.properties.network",
    "train": "grounder.properties.network",
    "evaluate": "grounder.properties.network",
    "generate_dataset": "grounder.properties.training_data",
    "MATERIALS": "grounder.properties.materials",
}
__getattr__ = lazy_attributes(__name__, _LAZY)

if TYPE_CHECKING:
    from grounder.properties.materials import MATERIALS
    from grounder.properties.model_files import WEIGHTS_DIR, PropertyModelError
    from grounder.properties.network import TrainOptions, evaluate, train
    from grounder.properties.prior import (
        ObjectProperties,
        PropertyModel,
        decode_embedding,
        load_property_model,
        predict_properties,
        sample_scene_variants,
        write_scene_variants,
    )
    from grounder.properties.training_data import generate_dataset

__all__ = [
    "MATERIALS",
    "WEIGHTS_DIR",
    "ObjectProperties",
    "PropertyModel",
    "PropertyModelError",
    "TrainOptions",
    "decode_embedding",
    "evaluate",
    "generate_dataset",
    "load_property_model",
    "predict_properties",
    "sample_scene_variants",
    "train",
    "write_scene_variants",
]
