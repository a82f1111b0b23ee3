from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_mbmf.envs import (
    OBSERVATION_KEY,
    STATE_KEY,
    LearnedDynamicsEnv,
    make_gym_state_env,
    make_half_cheetah_env,
)
from torchrl_mbmf.modules import DeltaDynamicsModel


@pytest.fixture(scope="module")
def cheetah():
    return make_half_cheetah_env(seed=0)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    m = DeltaDynamicsModel(18, 6, hidden_sizes=(32, 32))
    s = torch.randn(100, 18)
    m.fit_normalizer(
        s, torch.rand(100, 6) * 2 - 1, s + 0.1 * torch.randn(100, 18), torch.randn(100)
    )
    return m


@pytest.mark.parametrize("batch_size", [(), (4,), (2, 3)])
def test_check_env_specs_any_batch(cheetah, model, batch_size):
    env = LearnedDynamicsEnv(model, cheetah, batch_size=batch_size)
    check_env_specs(env)
    assert env.observation_spec[STATE_KEY].shape == (*batch_size, 18)
    assert env.observation_spec[OBSERVATION_KEY].shape == (*batch_size, 17)
    assert env.action_spec.shape == (*batch_size, 6)
    # only the model's state and observation, no physics info entries
    assert set(env.observation_spec.keys()) == {STATE_KEY, OBSERVATION_KEY}
    assert not env.batch_locked


def test_specs_from_batched_real_env(model):
    real = make_half_cheetah_env(num_envs=3, seed=0)
    env = LearnedDynamicsEnv(model, real)
    assert env.batch_size == ()
    check_env_specs(env)
    torch.testing.assert_close(env.action_spec.space.low, -torch.ones(6))


def test_starts_from_given_state_and_never_done(cheetah, model):
    env = LearnedDynamicsEnv(model, cheetah)
    real_td = cheetah.reset()
    start = real_td.expand(2, 15).clone()
    td0 = env.reset(start)
    torch.testing.assert_close(td0[STATE_KEY], start[STATE_KEY])
    actions = torch.rand(2, 15, 10, 6) * 2 - 1
    roll = env.rollout(
        10,
        policy=_Replay(actions),
        tensordict=td0,
        auto_reset=False,
        break_when_any_done=False,
    )
    assert roll.batch_size == (2, 15, 10)
    assert not roll["next", "done"].any()
    # the rollout is the model applied step by step, observation kept in sync
    s = start[STATE_KEY]
    for t in range(10):
        s, r = model(s, actions[..., t, :])
        torch.testing.assert_close(roll["next", STATE_KEY][..., t, :], s)
        torch.testing.assert_close(roll["next", "reward"][..., t, :], r)
    torch.testing.assert_close(roll["next", OBSERVATION_KEY], roll["next", STATE_KEY][..., 1:])


class _Replay:
    """Policy that writes precomputed actions, one time step per call."""

    def __init__(self, actions):
        self.actions = actions
        self.t = 0

    def __call__(self, td):
        td.set("action", self.actions[..., self.t, :])
        self.t += 1
        return td


def test_predict_matches_step(cheetah, model):
    env = LearnedDynamicsEnv(model, cheetah)
    td = env.reset(cheetah.reset().expand(5).clone())
    td["action"] = torch.rand(5, 6) * 2 - 1
    out = env.step(td)
    nxt, r = env.predict(td[STATE_KEY], td["action"])
    torch.testing.assert_close(out["next", STATE_KEY], nxt)
    torch.testing.assert_close(out["next", "reward"], r)
    torch.testing.assert_close(env.observation(nxt), nxt[..., 1:])


def test_reset_without_state_starts_from_real_initial_states(model):
    real = make_half_cheetah_env(seed=3)
    env = LearnedDynamicsEnv(model, real)
    td = env.reset()
    # HalfCheetah's initial state: qpos noise U(-0.1, 0.1), qvel noise 0.1 N(0, 1): never zero
    assert td[STATE_KEY].shape == (18,) and bool((td[STATE_KEY] != 0).any())
    assert float(td[STATE_KEY][:9].abs().max()) <= 0.1
    td = env.reset(TensorDict(batch_size=[4]))
    assert td[STATE_KEY].shape == (4, 18)
    assert len({tuple(s.tolist()) for s in td[STATE_KEY]}) == 4  # four different resets
    # the same initial states as the real env's own resets under the same seed
    real.set_seed(7)
    first = env.reset(TensorDict(batch_size=[2]))[STATE_KEY]
    real.set_seed(7)
    torch.testing.assert_close(first[0], real.reset()[STATE_KEY])
    torch.testing.assert_close(first[1], real.reset()[STATE_KEY])
    rollout = env.rollout(3)
    assert not bool((rollout[STATE_KEY][0] == 0).all())


def test_pendulum_without_dropped_dims():
    real = make_gym_state_env("Pendulum-v1", seed=0)
    env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
    check_env_specs(env)
    td = env.rollout(3, tensordict=env.reset(real.reset()), auto_reset=False)
    torch.testing.assert_close(td["next", OBSERVATION_KEY], td["next", STATE_KEY])


def test_errors_name_the_mismatch(cheetah, model):
    with pytest.raises(ValueError, match="state_dim=17"):
        LearnedDynamicsEnv(DeltaDynamicsModel(17, 6, hidden_sizes=(4,)), cheetah)
    with pytest.raises(ValueError, match="action_dim=5"):
        LearnedDynamicsEnv(DeltaDynamicsModel(18, 5, hidden_sizes=(4,)), cheetah)
    with pytest.raises(KeyError, match="'nope'"):
        LearnedDynamicsEnv(model, cheetah, state_key="nope")
    with pytest.raises(TypeError, match="DeltaDynamicsModel"):
        LearnedDynamicsEnv(torch.nn.Linear(3, 3), cheetah)
    env = LearnedDynamicsEnv(model, cheetah)
    with pytest.raises(ValueError, match="last dim 5"):
        env.reset(TensorDict(state=torch.zeros(2, 5), batch_size=[2]))


def _standing_still(state_dim: int, action_dim: int) -> DeltaDynamicsModel:
    """A model whose every prediction is ``s' = s`` with reward 0."""
    model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=(8,))
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
    return model


@pytest.fixture(scope="module")
def hopper():
    return make_gym_state_env("Hopper-v5", seed=0, exclude_current_positions_from_observation=False)


def test_hopper_terminations_follow_the_task_rule(hopper):
    env = LearnedDynamicsEnv(_standing_still(12, 3), hopper)
    check_env_specs(env)
    start = hopper.reset().expand(3).clone()
    start[STATE_KEY][:, 1] = torch.tensor([1.25, 0.5, 1.25])  # height: fine, fallen, fine
    start[STATE_KEY][2, 2] = 0.3  # torso angle beyond 0.2
    start[OBSERVATION_KEY] = env.observation(start[STATE_KEY])
    td = env.step(env.reset(start).set("action", torch.zeros(3, 3)))
    expected = torch.tensor([[False], [True], [True]])
    assert torch.equal(td["next", "terminated"], expected)
    assert torch.equal(td["next", "done"], expected)
    assert not env.never_terminates


def test_termination_fn_argument_and_its_checks(cheetah, model):
    assert LearnedDynamicsEnv(model, cheetah).never_terminates
    env = LearnedDynamicsEnv(
        _standing_still(18, 6), cheetah, termination_fn=lambda s: s[..., 0] > 1.0
    )
    start = cheetah.reset().expand(2).clone()
    start[STATE_KEY][:, 0] = torch.tensor([0.0, 2.0])
    td = env.step(env.reset(start).set("action", torch.zeros(2, 6)))
    assert td["next", "terminated"][:, 0].tolist() == [False, True]
    with pytest.raises(ValueError, match="bool tensor"):
        LearnedDynamicsEnv(model, cheetah, termination_fn=lambda s: s[..., 0])
    with pytest.raises(TypeError, match="termination_fn"):
        LearnedDynamicsEnv(model, cheetah, termination_fn=3)


def test_action_bounds_come_from_the_env():
    pendulum = make_gym_state_env("Pendulum-v1", seed=0)  # actions in [-2, 2]
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    assert model.action_bounds is None  # no clip of its own by default
    s = torch.zeros(1, 3)
    # without bounds the model tells 2.0 from 1.0
    assert not torch.equal(model(s, torch.full((1, 1), 2.0))[0], model(s, torch.ones(1, 1))[0])
    LearnedDynamicsEnv(model, pendulum)
    assert model.action_bounds == (-2.0, 2.0)  # adopted from the spec
    torch.testing.assert_close(model(s, torch.full((1, 1), 5.0)), model(s, torch.full((1, 1), 2.0)))
    LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, action_low=-2.0, action_high=2.0), pendulum)
    with pytest.raises(ValueError, match=r"\[-1.0, 1.0\].*'action' spec is \[-2.0, 2.0\]"):
        LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, action_low=-1.0, action_high=1.0), pendulum)
    inverted = make_gym_state_env("InvertedPendulum-v5", seed=0)  # actions in [-3, 3]
    model = DeltaDynamicsModel(4, 1, hidden_sizes=(8,))
    LearnedDynamicsEnv(model, inverted)
    assert model.action_bounds == (-3.0, 3.0)


def test_plain_gym_env_any_keys():
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    from torchrl_mbmf.modules import PolicyGuidedMPCPlanner, make_ppo_actor_critic

    real = GymEnv("Pendulum-v1")  # one "observation" entry: the state is what the policy reads
    env = LearnedDynamicsEnv(
        DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real, state_key="observation"
    )
    assert env.observation_key is None
    check_env_specs(env)
    actor, _ = make_ppo_actor_critic(real, hidden_sizes=(8,))
    planner = PolicyGuidedMPCPlanner(env, actor, num_candidates=4, horizon=3)
    td = real.rollout(3, planner)
    assert td["action"].shape == (3, 1) and bool((td["action"].abs() <= 2).all())
    # a float64 env is refused with the transform that fixes it
    hopper = GymEnv("Hopper-v5", exclude_current_positions_from_observation=False)
    with pytest.raises(TypeError, match="DoubleToFloat"):
        LearnedDynamicsEnv(DeltaDynamicsModel(12, 3), hopper, state_key="observation")
    hopper = TransformedEnv(hopper, DoubleToFloat())
    env = LearnedDynamicsEnv(
        DeltaDynamicsModel(12, 3, hidden_sizes=(8,)),
        hopper,
        state_key="observation",
        observation_key=None,
    )
    check_env_specs(env)
    assert not env.never_terminates  # Hopper's rule found through the transform
    renamed = make_gym_state_env("Pendulum-v1", state_key="s", observation_key="obs")
    env = LearnedDynamicsEnv(
        DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), renamed, state_key="s", observation_key="obs"
    )
    check_env_specs(env)
    assert set(env.observation_spec.keys()) == {"s", "obs"}


def test_fit_and_dataset_read_the_same_state_key():
    from torchrl.envs import GymEnv

    from torchrl_mbmf.data import collect_random_transitions
    from torchrl_mbmf.world_model import fit_dynamics

    real = GymEnv("Pendulum-v1")
    data = collect_random_transitions(real, 300, seed=0, state_key="observation")
    assert data.state_key == "observation"
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(16,))
    LearnedDynamicsEnv(model, real, state_key="observation")  # adopts [-2, 2] before the fit
    history = fit_dynamics(model, data, batch_size=64, max_epochs=2, seed=0)
    assert len(history.val_loss) == 2
    with pytest.raises(ValueError, match="state_key='state' but the dataset stores 'observation'"):
        fit_dynamics(model, data, max_epochs=1, state_key="state")
    # a TensorDict of transitions under other keys: the same fit as under the default ones
    td = data.tensors().clone()
    renamed = td.clone()
    renamed.rename_key_("observation", "obs")
    renamed.rename_key_(("next", "observation"), ("next", "obs"))
    td.rename_key_("observation", "state")
    td.rename_key_(("next", "observation"), ("next", "state"))
    fits = []
    for transitions, key in ((td, None), (renamed, "obs")):
        torch.manual_seed(0)
        m = DeltaDynamicsModel(3, 1, hidden_sizes=(16,), action_low=-2.0, action_high=2.0)
        fits.append(
            fit_dynamics(m, transitions, max_epochs=2, batch_size=64, seed=0, state_key=key)
        )
    assert fits[0].val_loss == fits[1].val_loss
    assert "state" not in set(renamed.keys())  # the caller's data is left as it was
    with pytest.raises(KeyError, match=r"no .*nope.* entry"):
        fit_dynamics(m, renamed, max_epochs=1, state_key="nope")


def test_learned_env_over_a_single_transform_env():
    """A TransformedEnv built with one transform holds it bare, not in a Compose."""
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    from torchrl_mbmf.envs import LearnedDynamicsEnv
    from torchrl_mbmf.modules import DeltaDynamicsModel

    real = TransformedEnv(GymEnv("Pendulum-v1"), DoubleToFloat())
    model_env = LearnedDynamicsEnv(
        DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real, state_key="observation"
    )
    assert model_env.rollout(3, tensordict=model_env.reset(real.reset()), auto_reset=False)[
        "next", "reward"
    ].shape == (3, 1)
