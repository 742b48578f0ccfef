"""make_vector_env / sb3_vec_env: the batch is the single environments, stepped together."""

from __future__ import annotations

import numpy as np
import pytest

from safelane import ConfigError, make_env, make_vector_env, sb3_vec_env

SHORT = {"env.duration": 4, "shield.mode": "robust"}  # 4-decision episodes: autoresets come quickly


def test_batch_equals_the_single_environments_across_autoresets() -> None:
    """Row i of the batch is make_env(seed=S+i) driven by the same actions: observations, rewards,
    masks, flags; a finished row restarts with the single env's next (unseeded) reset, and the final
    observation and mask are those of the single env's last step."""
    n, seed = 3, 11
    vector = make_vector_env("fast", num_envs=n, **SHORT)
    singles = [make_env("fast", simulator="fast", **SHORT) for _ in range(n)]
    obs, infos = vector.reset(seed=seed)
    single_obs = [env.reset(seed=seed + i) for i, env in enumerate(singles)]
    for i in range(n):
        assert np.array_equal(obs[i], single_obs[i][0])
        assert np.array_equal(infos["action_mask"][i], single_obs[i][1]["action_mask"])
    rng = np.random.default_rng(0)
    finished = 0
    for _ in range(10):
        actions = rng.integers(5, size=n)
        obs, rewards, terminated, truncated, infos = vector.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, info = env.step(int(actions[i]))
            assert rewards[i] == r and terminated[i] == te and truncated[i] == tr
            assert infos["fallback"][i] == info["fallback"] and infos["executed_action"][i] == info["executed_action"]
            if te or tr:
                finished += 1
                assert infos["_final_obs"][i] and np.array_equal(infos["final_obs"][i], o)
                assert np.array_equal(infos["final_action_mask"][i], info["action_mask"])
                assert infos["_episode"][i] and infos["episode"]["l"][i] == info["snapshot"].time * 1
                o, info = env.reset()
            assert np.array_equal(obs[i], o)
            assert np.array_equal(vector.action_masks()[i], info["action_mask"])
    assert finished >= n  # every environment went through at least one autoreset
    vector.close()


def test_same_seed_same_batch() -> None:
    runs = []
    for _ in range(2):
        vector = make_vector_env("fast", num_envs=4, seed=3, **SHORT)
        rng = np.random.default_rng(1)
        out = [vector.step(rng.integers(5, size=4))[0] for _ in range(6)]
        runs.append(np.stack(out))
        vector.close()
    assert np.array_equal(runs[0], runs[1])


def test_bad_num_envs_is_one_line() -> None:
    with pytest.raises(ConfigError, match="num_envs"):
        make_vector_env("fast", num_envs=0)


def _train(algorithm: str, steps: int) -> tuple[int, int]:
    """Train ``algorithm`` (MaskablePPO or PPO) for ``steps`` decisions on 4 shielded environments
    (no override): (decisions whose chosen action the mask forbade, decisions with a forbidden action)."""
    sb3_contrib = pytest.importorskip("sb3_contrib")
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    class Count(BaseCallback):
        unsafe = 0
        constrained = 0

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                Count.unsafe += int(info["unsafe_action"])
            Count.constrained += int((~vec.env_method("action_masks")[0]).any())
            return True

    vec = sb3_vec_env(make_vector_env("fast", num_envs=4, seed=0, **{"shield.mode": "robust"}))
    cls = sb3_contrib.MaskablePPO if algorithm == "maskable" else PPO
    model = cls("MlpPolicy", vec, n_steps=32, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=steps, callback=Count())
    vec.close()
    return Count.unsafe, Count.constrained


def test_maskable_ppo_never_takes_a_masked_action() -> None:
    """sb3-contrib's MaskablePPO reads the masks through env_method('action_masks'): over a few hundred
    decisions of training it never chooses a forbidden action, while plain PPO on the same batch
    does (so the count can fail), and the masks did forbid actions along the way."""
    unsafe, constrained = _train("maskable", 256)
    assert constrained > 0
    assert unsafe == 0
    unsafe_ppo, _ = _train("ppo", 256)
    assert unsafe_ppo > 0


def test_the_batch_kernels_cache_is_dropped_when_a_kernel_it_calls_changes(
    tmp_path: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    """numba keys a cache to its own file only; the batch's kernels compile in kernels of other files,
    so a changed digest of those files deletes the batch's cached kernels (and only then)."""
    from pathlib import Path

    from safelane.env import fast_batch

    cache = Path(str(tmp_path))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    (cache / "sub").mkdir()
    stale = cache / "sub" / "fast_batch._observe_rows-1.py311.nbi"
    other = cache / "sub" / "kernels.simulate-1.py311.nbi"
    stale.write_text("old")
    other.write_text("keep")
    (cache / "fast_batch.kernels.sha256").write_text("a digest of other sources")
    fast_batch._drop_stale_kernel_cache()
    assert not stale.exists() and other.exists()
    stale.write_text("fresh")  # compiled against the current sources: kept from now on
    fast_batch._drop_stale_kernel_cache()
    assert stale.exists()


def test_threads_give_the_same_rows() -> None:
    """Two numba threads share the batch's scenes: the same observations, rewards, masks and flags as
    one thread, step for step across autoresets."""
    rows = []
    for threads in (1, 2):
        vector = make_vector_env("fast", num_envs=6, seed=5, threads=threads, **SHORT)
        rng = np.random.default_rng(2)
        steps = [vector.step(rng.integers(5, size=6)) for _ in range(9)]
        rows.append(
            [(o, r, te, tr, i["action_mask"], i["fallback"], i["invariant_break"]) for o, r, te, tr, i in steps]
        )
        vector.close()
    for one, two in zip(*rows, strict=True):
        assert all(np.array_equal(a, b) for a, b in zip(one, two, strict=True))


def test_threads_outside_the_machine_is_one_line() -> None:
    with pytest.raises(ConfigError, match=r"threads: must be an integer in 1\.\."):
        make_vector_env("fast", num_envs=2, threads=0)
