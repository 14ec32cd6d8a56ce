"""The residual network's former modules still work for one release: importing one warns, naming
where its names went, and gives the very objects of the new modules."""

import importlib
import sys

import pytest

MOVED = {
    "ttsim_jax.physics.residual": {
        "ttsim_jax.physics.network": ["PAPER_BETA", "N_ATTENUATION_INPUTS", "ResidualConfig", "ResidualNet",
                                      "ResidualModel", "init_model", "init_variables", "residual_outputs",
                                      "sampled_residual", "gathered_residual", "beta_from_distance"],
        "ttsim_jax.physics.network_checkpoint": ["save_residual", "load_residual", "checkpoint_metadata",
                                                 "model_from_arrays", "READABLE_MODEL_VERSIONS"],
        "ttsim_jax.files.checkpoint": ["CheckpointError", "read_container", "write_container", "CHECKPOINT_MAGIC"],
        "ttsim_jax.errors": ["ConfigError"],
        "ttsim_jax.files.toml": ["read_toml"],
        "ttsim_jax.fit.network_config": ["load_residual_config", "residual_config_from_toml", "CONFIG_TABLES"],
        "ttsim_jax.fit.network_stats": ["kmeans", "calibrate_beta", "population_batch_stats", "calibration_scale",
                                        "ONE_SIGMA_COVERAGE"],
    },
    "ttsim_jax.fit.residual": {
        "ttsim_jax.fit.network_training": ["train_residual", "split_by_contact", "gaussian_nll", "TRAIN_STATE_KIND"],
        "ttsim_jax.fit.network_config": ["TrainConfig", "load_train_config"],
        "ttsim_jax.fit.network_evaluation": ["predict", "evaluate_residual", "evaluate_by_band", "calibrate_sigma",
                                             "contact_errors", "distance_bands", "COMPONENTS", "ERROR_NAMES"],
        "ttsim_jax.fit.synthetic_contacts": ["make_synthetic_contacts", "recovery_experiment", "true_residual",
                                             "standin_base_fn", "racket_base_fn", "sample_racket_inputs"],
    },
}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_module_warns_and_gives_the_new_objects(old):
    sys.modules.pop(old, None)  # a module imports (and warns) once per process
    with pytest.warns(DeprecationWarning, match=old.replace(".", r"\.") + " is deprecated") as caught:
        shim = importlib.import_module(old)
    message = str(caught[0].message)
    for new, names in MOVED[old].items():
        assert new in message, (new, message)
        module = importlib.import_module(new)
        for name in names:
            assert getattr(shim, name) is getattr(module, name), (old, name, new)
    for name in shim.__all__:
        assert hasattr(shim, name), name


def test_one_error_class_of_each_kind():
    from ttsim_jax import ConfigError as top
    from ttsim_jax.errors import ConfigError, UserError
    from ttsim_jax.files.checkpoint import CheckpointError
    from ttsim_jax.params import ConfigError as params_error
    from ttsim_jax.rl.checkpoint import CheckpointError as policy_error

    assert top is ConfigError and params_error is ConfigError and policy_error is CheckpointError
    for error in (ConfigError, CheckpointError):
        assert issubclass(error, UserError) and issubclass(error, ValueError)


def test_the_task_sections_residual_config_keeps_its_former_name():
    from ttsim_jax.env.config import ResidualConfig, TaskResidualConfig
    from ttsim_jax.physics.network import ResidualConfig as NetworkConfig

    assert ResidualConfig is TaskResidualConfig and TaskResidualConfig is not NetworkConfig
