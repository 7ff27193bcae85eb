import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3

from sb3_collapse import DrQv2
from sb3_collapse.common.layers import layer_parameters
from sb3_collapse.drqv2.encoders import PixelEncoder
from sb3_collapse.drqv2.transplant import (
    GROUP_LAYERS,
    TRANSPLANT_GROUPS,
    check_init_from,
    group_keys,
    load_sources,
    plan_transplant,
    source_key,
    transplant,
)
from tests.random_env import RandomObservationEnv

POLICY_KWARGS = {"hidden_dim": 32, "feature_dim": 16}
SMALL = {"buffer_size": 200, "learning_starts": 20, "batch_size": 8}
TARGET_SEED = 7


def pixel_env(channels=9, size=32):
    return RandomObservationEnv(gym.spaces.Box(0, 255, (channels, size, size), np.uint8), action_repeat=2)


def model(seed=TARGET_SEED, env=None, policy="CnnPolicy", policy_kwargs=None, **kwargs):
    return DrQv2(
        policy, env or pixel_env(), seed=seed, policy_kwargs=policy_kwargs or dict(POLICY_KWARGS), **SMALL, **kwargs
    )


def perturbed(source, seed):
    """Shift every entry (parameters and buffers) by seeded noise: no entry equals a fresh model's any more,
    not even the zero biases and unit LayerNorm scales, and the source's target critic differs from its critic."""
    generator = th.Generator().manual_seed(seed)
    with th.no_grad():
        for value in source.policy.state_dict().values():
            value.add_(th.randn(value.shape, generator=generator, dtype=value.dtype))
    return source


def state(m):
    return {key: value.detach().clone() for key, value in m.policy.state_dict().items()}


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sources")
    good, bad = perturbed(model(seed=1), 101), perturbed(model(seed=2), 102)
    good.save(folder / "good.zip")
    bad.save(folder / "bad.zip")
    return {"good": (folder / "good.zip", state(good)), "bad": (folder / "bad.zip", state(bad))}


@pytest.fixture(scope="module")
def blank():
    return state(model())


def test_groups_are_the_named_layers_and_cover_the_policy():
    policy = model().policy
    keys = list(policy.state_dict())
    names = {id(p): name for name, p in policy.named_parameters()}
    layers = layer_parameters(policy)
    for group in ("cnn", "mlp"):
        named = sorted(names[id(p)] for layer in GROUP_LAYERS[group] for p in layers[layer])
        assert sorted(group_keys(keys, group)) == named, group
    assert GROUP_LAYERS["cnn"] + GROUP_LAYERS["mlp"] == tuple(name for name in layers)
    assert group_keys(keys, "critic") == [k for k in keys if k.split(".")[0] in ("critic", "critic_target")]
    # Every entry belongs to exactly one group: a transplant of all three replaces the whole policy.
    assert sorted(k for group in TRANSPLANT_GROUPS for k in group_keys(keys, group)) == sorted(keys)
    assert source_key("critic_target.q1.0.weight") == "critic.q1.0.weight"
    assert source_key("actor.trunk.1.bias") == "actor.trunk.1.bias"


@pytest.mark.parametrize(
    "init_from",
    [
        {"cnn": "good"},
        {"mlp": "bad"},
        {"critic": "good"},
        {"cnn": "good", "mlp": "bad"},
        {"cnn": "bad", "mlp": "good", "critic": "bad"},
    ],
)
def test_transplant_copies_exactly_the_named_groups(sources, blank, init_from):
    th.manual_seed(123)  # the global generator before the build must not matter: the seed decides
    paths = {group: str(sources[name][0]) for group, name in init_from.items()}
    target = model(init_from=paths)

    copied = {key: init_from[group] for group in init_from for key in group_keys(blank, group)}
    result = state(target)
    assert list(result) == list(blank)
    for key, value in result.items():
        if key in copied:
            expected = sources[copied[key]][1][source_key(key)]
            assert not th.equal(expected, blank[key]), key  # the check below can tell them apart
            assert th.equal(value, expected), f"{key} should be the {copied[key]} source's {source_key(key)}"
        else:
            assert th.equal(value, blank[key]), f"{key} should be the blank model's"

    assert target.init_from == {group: str(sources[name][0].resolve()) for group, name in init_from.items()}
    assert all(not optimizer.state for optimizer in target.policy.optimizers)
    assert target.replay_buffer.size() == 0
    assert target.num_timesteps == 0 and target._n_updates == 0 and target.reset_step == 0
    assert target.encoder.cnn1[0].weight.is_contiguous(memory_format=th.channels_last)


def test_reading_sources_draws_no_random_number(sources):
    model(init_from={"cnn": str(sources["good"][0]), "mlp": str(sources["bad"][0])})
    after_transplant = th.random.get_rng_state(), np.random.get_state()[1]
    model()
    assert th.equal(th.random.get_rng_state(), after_transplant[0])
    assert np.array_equal(np.random.get_state()[1], after_transplant[1])


def test_in_memory_source_and_path_without_suffix(sources):
    source = perturbed(model(seed=3), 103)
    stem = str(sources["good"][0]).removesuffix(".zip")
    target = model(init_from={"critic": source, "cnn": stem})
    assert target.init_from == {"cnn": stem + ".zip", "critic": "<in-memory DrQv2, seed 3, 0 agent steps>"}
    for key in group_keys(target.policy.state_dict(), "critic"):
        assert th.equal(target.policy.state_dict()[key], source.policy.state_dict()[source_key(key)])
    # The source is copied, not shared.
    assert target.critic.trunk[0].weight.data_ptr() != source.critic.trunk[0].weight.data_ptr()


def test_trains_after_transplant_and_save_load_keeps_trained_weights(sources, tmp_path):
    good, bad = (str(sources[name][0]) for name in ("good", "bad"))
    target = model(init_from={"cnn": good, "mlp": bad})
    before = state(target)
    target.learn(30)
    assert target._n_updates > 0
    after = state(target)
    for prefix in ("encoder.cnn1", "actor.trunk", "actor.mlp1", "critic.q1", "critic_target.q1"):
        assert any(not th.equal(after[k], before[k]) for k in after if k.startswith(prefix)), prefix

    target.save(tmp_path / "trained.zip")
    loaded = DrQv2.load(tmp_path / "trained.zip", env=pixel_env())
    assert loaded.init_from == target.init_from
    restored = state(loaded)
    assert all(th.equal(restored[k], after[k]) for k in after)  # trained weights, not transplanted again
    with pytest.raises(TypeError, match="does not transplant"):
        DrQv2.load(tmp_path / "trained.zip", init_from={"cnn": good})


def test_reset_from_scratch_does_not_transplant_again(sources):
    path, source = sources["good"]
    target = model(init_from={"mlp": str(path)})
    target.reset_from_scratch()
    for key in group_keys(source, "mlp"):  # new random weights (the source's are all shifted by noise)
        assert not th.equal(target.policy.state_dict()[key], source[key]), key
    assert target.init_from == {"mlp": str(path.resolve())}


class BufferedPixelEncoder(PixelEncoder):
    """A pixel encoder with a buffer, to check that buffers are transplanted too."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register_buffer("scale", th.ones(3))


def test_buffers_are_copied_too():
    kwargs = dict(POLICY_KWARGS, encoder_class=BufferedPixelEncoder)
    source = perturbed(model(seed=4, policy_kwargs=kwargs), 104)
    target = model(policy_kwargs=kwargs, init_from={"cnn": source})
    assert th.equal(target.encoder.scale, source.encoder.scale) and not th.equal(target.encoder.scale, th.ones(3))


def test_shape_mismatch_names_the_parameter_and_the_cause(sources):
    good = str(sources["good"][0])
    with pytest.raises(ValueError, match=r"actor\.trunk\.0\.weight.*\(16, 2592\).*\(8, 2592\).*feature_dim=16.*8"):
        model(policy_kwargs={"hidden_dim": 32, "feature_dim": 8}, init_from={"mlp": good})
    with pytest.raises(ValueError, match=r"encoder\.cnn1\.0\.weight.*\(32, 9, 3, 3\).*\(32, 6, 3, 3\).*frame_stack"):
        model(env=pixel_env(channels=6), init_from={"cnn": good})
    with pytest.raises(ValueError, match=r"critic\.q1\.0\.weight.*hidden_dim=32"):
        model(policy_kwargs={"hidden_dim": 16, "feature_dim": 16}, init_from={"critic": good})
    # The convolutions do not depend on the image size: a CNN from 32x32 images fits 40x40 ones.
    bigger = model(env=pixel_env(size=40), init_from={"cnn": good})
    assert th.equal(bigger.encoder.cnn4[0].weight, sources["good"][1]["encoder.cnn4.0.weight"])
    with pytest.raises(ValueError, match=r"actor\.trunk\.0\.weight.*observation shape"):
        model(env=pixel_env(size=40), init_from={"mlp": good})
    with pytest.raises(ValueError, match="channels_last=True.*channels_last=False"):
        no_channels_last = dict(POLICY_KWARGS, encoder_kwargs={"channels_last": False})
        model(policy_kwargs=no_channels_last, init_from={"mlp": good})


def test_mismatch_is_found_before_anything_is_copied(sources):
    policy = model(policy_kwargs={"hidden_dim": 32, "feature_dim": 8}).policy
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    loaded = load_sources(check_init_from({"cnn": sources["good"][0], "mlp": sources["bad"][0]}))
    with pytest.raises(ValueError, match="actor.trunk.0.weight"):
        transplant(policy, loaded)  # "cnn" fits, "mlp" does not
    assert all(th.equal(v, before[k]) for k, v in policy.state_dict().items())
    assert set(plan_transplant(policy, {"cnn": loaded["cnn"]})) == set(group_keys(before, "cnn"))


def test_mlp_policy_transplants_the_actor_and_has_no_cnn(sources):
    state_env = RandomObservationEnv(gym.spaces.Box(-1, 1, (5,), np.float32))
    source = perturbed(model(seed=5, env=state_env, policy="MlpPolicy"), 105)
    target = model(env=state_env, policy="MlpPolicy", init_from={"mlp": source})
    assert th.equal(target.actor.mlp2[0].weight, source.actor.mlp2[0].weight)
    with pytest.raises(ValueError, match="no 'cnn' weights.*MlpPolicy has no CNN"):
        model(env=state_env, policy="MlpPolicy", init_from={"cnn": source})
    with pytest.raises(ValueError, match="source .*MlpPolicy.* has no 'cnn' weights"):
        model(init_from={"cnn": source})
    with pytest.raises(ValueError, match=r"actor\.trunk\.0\.weight.*policy='MlpPolicy'.*'CnnPolicy'"):
        model(init_from={"mlp": source})


def test_bad_init_from_gives_clear_errors(sources, tmp_path):
    good = sources["good"][0]
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['encoder'\].*'cnn', 'mlp', 'critic'"):
        model(init_from={"encoder": good})
    with pytest.raises(TypeError, match="must be a dict"):
        model(init_from=[good])
    with pytest.raises(TypeError, match=r"init_from\['mlp'\] must be the path"):
        model(init_from={"mlp": 3})
    with pytest.raises(FileNotFoundError, match=r"init_from\['cnn'\].*missing\.zip.*does not exist"):
        model(init_from={"cnn": tmp_path / "missing.zip"})

    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match=r"init_from\['cnn'\].*corrupt\.zip.*is not a zip file"):
        model(init_from={"cnn": corrupt})
    truncated = tmp_path / "truncated.zip"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"truncated\.zip"):
        model(init_from={"cnn": truncated})
    damaged = tmp_path / "damaged.zip"
    with zipfile.ZipFile(good) as archive, zipfile.ZipFile(damaged, "w") as out:
        out.writestr("data", archive.read("data"))
        out.writestr("policy.pth", b"garbage")
    with pytest.raises(ValueError, match=r"damaged\.zip.*'policy.pth' could not be read.*corrupt"):
        model(init_from={"cnn": damaged})
    other = tmp_path / "other.zip"
    with zipfile.ZipFile(other, "w") as out:
        out.writestr("readme.txt", "hello")
    with pytest.raises(ValueError, match=r"not an SB3 model.*\['data', 'policy.pth'\]"):
        model(init_from={"cnn": other})

    td3 = TD3(
        "MlpPolicy",
        RandomObservationEnv(gym.spaces.Box(-1, 1, (5,), np.float32)),
        buffer_size=10,
        policy_kwargs={"net_arch": [8]},
    )
    td3.save(tmp_path / "td3.zip")
    with pytest.raises(ValueError, match=r"td3\.zip.*not a DrQv2 model.*stable_baselines3\.td3\.policies"):
        model(init_from={"mlp": tmp_path / "td3.zip"})
    with pytest.raises(TypeError, match=r"init_from\['mlp'\]: a TD3 model cannot be transplanted"):
        model(init_from={"mlp": td3})
