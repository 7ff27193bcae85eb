import errno
import json
import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.errors import CheckpointError, InputError
from sb3_collapse.run import replay_checkpoint
from sb3_collapse.run.replay_checkpoint import ReplayStore

FRAME = (3, 8, 8)
FRAME_STACK = 3
OBSERVATIONS = gym.spaces.Box(0, 255, (FRAME[0] * FRAME_STACK, *FRAME[1:]), np.uint8)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def make_buffer(buffer_size=24, n_envs=1, sampling="sb3", min_episode_length=5):
    return FrameStackReplayBuffer(
        buffer_size * n_envs,
        OBSERVATIONS,
        ACTIONS,
        "cpu",
        n_envs=n_envs,
        n_steps=3,
        gamma=0.9,
        frame_stack=FRAME_STACK,
        min_episode_length=min_episode_length,
        sampling=sampling,
    )


class Stream:
    """``add`` arguments of random episodes (1-12 agent steps, ending by termination or time limit) of n envs."""

    def __init__(self, n_envs, seed):
        self.rng = np.random.default_rng(seed)
        self.n_envs = n_envs
        self.obs = np.stack([self._reset_obs() for _ in range(n_envs)])

    def _reset_obs(self):
        return np.concatenate([self.rng.integers(0, 256, FRAME, dtype=np.uint8)] * FRAME_STACK)

    def add(self, buffers, steps):
        """Add the next ``steps`` transitions to every buffer of ``buffers`` (the same ones)."""
        for _ in range(steps):
            new = self.rng.integers(0, 256, (self.n_envs, *FRAME), dtype=np.uint8)
            next_obs = np.concatenate([self.obs[:, FRAME[0] :], new], axis=1)
            terminated = self.rng.random(self.n_envs) < 0.08
            truncated = self.rng.random(self.n_envs) < 0.08
            dones = terminated | truncated
            infos = [{"TimeLimit.truncated": bool(tr and not te)} for te, tr in zip(terminated, truncated)]
            action = self.rng.uniform(-1, 1, (self.n_envs, 2)).astype(np.float32)
            reward = self.rng.normal(size=self.n_envs)
            for buffer in buffers:
                buffer.add(self.obs, next_obs, action, reward, dones, infos)
            self.obs = next_obs.copy()
            for i in np.flatnonzero(dones):
                self.obs[i] = self._reset_obs()


SCALARS = ("pos", "full", "transitions_added", "resets")
SCALAR_ARRAYS = ("frame_heads", "steps_since_done", "episodes_done")


def assert_same_state(saved, restored, whole_arrays=True):
    """Counters equal; arrays equal (whole, or where written since the last reset); same samples for a seed."""
    for name in SCALARS:
        assert getattr(saved, name) == getattr(restored, name), name
    for name in SCALAR_ARRAYS:
        np.testing.assert_array_equal(getattr(saved, name), getattr(restored, name), err_msg=name)
    if whole_arrays:
        for name, array in saved.storage_arrays.items():
            np.testing.assert_array_equal(array, restored.storage_arrays[name], err_msg=name)
    else:
        live = np.arange(saved.buffer_size if saved.full else saved.pos)
        for name in replay_checkpoint.TRANSITION_ARRAYS:
            np.testing.assert_array_equal(getattr(saved, name)[live], getattr(restored, name)[live], err_msg=name)
        for env, head in enumerate(saved.frame_heads):
            slots = np.arange(max(0, head - saved.frame_capacity), head) % saved.frame_capacity
            np.testing.assert_array_equal(saved.frames[slots, env], restored.frames[slots, env])
    assert saved.ready_to_sample == restored.ready_to_sample
    if saved.ready_to_sample:
        for seed in (0, 1):
            np.random.seed(seed)
            expected = saved.sample(16)
            np.random.seed(seed)
            got = restored.sample(16)
            for field in expected._fields:
                assert th.equal(getattr(expected, field), getattr(got, field)), field


def through_json(manifest):
    return json.loads(json.dumps(manifest))


def chunk_files(folder):
    return sorted(name for name in os.listdir(folder) if name.startswith(replay_checkpoint.CHUNK_PREFIX))


def listed(manifest):
    return {chunk["file"] for chunk in manifest["chunks"]}


def new_bytes(buffer, transitions, frames):
    """Bytes a chunk takes for these counts of new transitions and frames (all envs)."""
    row = sum(getattr(buffer, name)[0].nbytes for name in replay_checkpoint.TRANSITION_ARRAYS)
    return transitions * row + frames * buffer.frames[0, 0].nbytes


@pytest.mark.parametrize("n_envs, sampling", [(1, "sb3"), (2, "drqv2"), (2, "sb3")])
def test_save_restore_round_trip_and_resume(tmp_path, n_envs, sampling):
    """Saves at random points (before, at and after wrap-arounds, several wraps): each restores exactly, and a
    restored buffer that goes on receiving the same transitions stays equal to the original."""
    rng = np.random.default_rng(n_envs)
    buffer = make_buffer(n_envs=n_envs, sampling=sampling)
    stream = Stream(n_envs, seed=3)
    store = ReplayStore(tmp_path / "replay")
    for steps in [1, 5, 18, 0, 24, 7, 60, 3] + list(rng.integers(1, 30, 6)):
        stream.add([buffer], int(steps))
        manifest = through_json(store.save(buffer))
        restored = make_buffer(n_envs=n_envs, sampling=sampling)
        ReplayStore(tmp_path / "replay").restore(restored, manifest)
        assert_same_state(buffer, restored)
    # Resume: the restored buffer and the original receive the same transitions, and checkpoint on.
    resumed_store = ReplayStore(tmp_path / "replay")
    resumed = make_buffer(n_envs=n_envs, sampling=sampling)
    resumed_store.restore(resumed, manifest)
    for steps in (4, 30):
        stream.add([buffer, resumed], steps)
        assert_same_state(buffer, resumed)
        manifest = through_json(resumed_store.save(resumed))
        again = make_buffer(n_envs=n_envs, sampling=sampling)
        ReplayStore(tmp_path / "replay").restore(again, manifest)
        assert_same_state(buffer, again)


def test_saves_are_incremental(tmp_path):
    """A save writes the new transitions and frames only, as new files; earlier files are not modified."""
    buffer = make_buffer(buffer_size=40)
    stream = Stream(1, seed=0)
    store = ReplayStore(tmp_path)
    stream.add([buffer], 10)
    first = store.save(buffer)
    assert store.bytes_needed(first) == new_bytes(buffer, 10, int(buffer.frame_heads[0]))
    before = {name: (tmp_path / name).read_bytes() for name in chunk_files(tmp_path)}
    heads = int(buffer.frame_heads[0])
    stream.add([buffer], 7)
    second = store.save(buffer)
    added = second["chunks"][len(first["chunks"]) :]
    assert second["chunks"][: len(first["chunks"])] == first["chunks"]
    expected = new_bytes(buffer, 7, int(buffer.frame_heads[0]) - heads)
    assert sum(chunk["bytes"] for chunk in added) == expected
    assert sum((tmp_path / chunk["file"]).stat().st_size for chunk in added) == expected
    assert {name: (tmp_path / name).read_bytes() for name in before} == before
    assert store.save(buffer)["chunks"] == second["chunks"]  # nothing new: nothing written
    assert len(chunk_files(tmp_path)) == len(second["chunks"])


def test_more_than_the_rings_hold_between_saves(tmp_path):
    """After several wraps between two saves, only the rings' content is written and older chunks are dropped."""
    buffer = make_buffer(buffer_size=20)
    stream = Stream(1, seed=1)
    store = ReplayStore(tmp_path)
    stream.add([buffer], 6)
    first = store.save(buffer)
    stream.add([buffer], 75)
    second = store.save(buffer)
    assert not {chunk["file"] for chunk in first["chunks"]} & {chunk["file"] for chunk in second["chunks"]}
    assert store.bytes_needed(second) == new_bytes(buffer, buffer.buffer_size, buffer.frame_capacity)
    restored = make_buffer(buffer_size=20)
    store.restore(restored, second)
    assert_same_state(buffer, restored)


def test_reset_starts_a_new_chain(tmp_path):
    """After buffer.reset(), a save writes the new data from scratch and the manifest drops the earlier chunks."""
    buffer = make_buffer(buffer_size=20)
    stream = Stream(1, seed=2)
    store = ReplayStore(tmp_path)
    stream.add([buffer], 30)
    before = store.save(buffer)
    buffer.reset()
    stream.add([buffer], 6)
    after = store.save(buffer)
    assert not {chunk["file"] for chunk in before["chunks"]} & {chunk["file"] for chunk in after["chunks"]}
    assert store.bytes_needed(after) == new_bytes(buffer, 6, int(buffer.frame_heads[0]))
    restored = make_buffer(buffer_size=20)
    store.restore(restored, through_json(after))
    assert restored.resets == 1 and restored.transitions_added == 6
    assert_same_state(buffer, restored, whole_arrays=False)  # the original keeps stale rows behind pos


def test_reset_then_more_than_before_is_not_mistaken_for_new_data(tmp_path):
    """Counters past their values at the last save after a reset: the resets counter tells the save to start over."""
    buffer = make_buffer(buffer_size=20)
    stream = Stream(1, seed=11)
    store = ReplayStore(tmp_path)
    stream.add([buffer], 5)
    store.save(buffer)
    buffer.reset()
    stream.add([buffer], 12)
    manifest = store.save(buffer)
    assert store.bytes_needed(manifest) == new_bytes(buffer, 12, int(buffer.frame_heads[0]))
    restored = make_buffer(buffer_size=20)
    store.restore(restored, manifest)
    assert_same_state(buffer, restored, whole_arrays=False)


def test_collect_garbage_keeps_exactly_what_is_needed(tmp_path):
    buffer = make_buffer(buffer_size=20)
    stream = Stream(1, seed=4)
    store = ReplayStore(tmp_path, max_file_bytes=1500)  # several files per save
    manifests = []
    for _ in range(8):
        stream.add([buffer], 9)
        manifests.append(store.save(buffer))
    assert len(manifests[-1]["chunks"]) > 2
    (tmp_path / ".chunk-000999-00000000.bin.tmp").write_bytes(b"partial")  # a save killed mid-write
    (tmp_path / "notes.txt").write_text("not ours")
    kept = listed(manifests[-3]) | listed(manifests[-1])
    doomed = sum((tmp_path / name).stat().st_size for name in set(chunk_files(tmp_path)) - kept)
    assert doomed > 0
    assert store.collect_garbage(keep=[manifests[-3], manifests[-1]]) == doomed + len(b"partial")
    assert set(chunk_files(tmp_path)) == kept
    assert not store.collect_garbage(keep=[manifests[-3], manifests[-1]])
    store.collect_garbage(keep=[])  # the store's own last save stays: the base of its next one
    assert set(chunk_files(tmp_path)) == listed(manifests[-1])
    assert (tmp_path / "notes.txt").exists()
    assert sum((tmp_path / name).stat().st_size for name in chunk_files(tmp_path)) == store.bytes_needed(manifests[-1])
    restored = make_buffer(buffer_size=20)
    ReplayStore(tmp_path).restore(restored, manifests[-1])
    assert_same_state(buffer, restored)


def test_disk_stays_near_the_buffer_size_after_many_wraps(tmp_path):
    """The chunks a manifest lists hold the rings' data plus at most one partly overwritten file per ring."""
    buffer = make_buffer(buffer_size=50, min_episode_length=20)
    stream = Stream(1, seed=5)
    max_file_bytes = 4000
    store = ReplayStore(tmp_path, max_file_bytes=max_file_bytes)
    ring_bytes = new_bytes(buffer, buffer.buffer_size, buffer.frame_capacity)
    for _ in range(30):
        stream.add([buffer], 13)
        manifest = store.save(buffer)
        store.collect_garbage(keep=[manifest])
        assert store.bytes_needed(manifest) <= ring_bytes + 2 * max_file_bytes
        assert store.disk_bytes() == store.bytes_needed(manifest)


@pytest.mark.parametrize("damage", ["missing", "truncated", "corrupt", "longer"])
def test_damaged_chunk_is_a_clear_error(tmp_path, damage):
    buffer = make_buffer()
    stream = Stream(1, seed=6)
    store = ReplayStore(tmp_path)
    stream.add([buffer], 10)
    store.save(buffer)
    stream.add([buffer], 10)
    manifest = store.save(buffer)
    path = tmp_path / manifest["chunks"][-1]["file"]
    data = bytearray(path.read_bytes())
    if damage == "missing":
        path.unlink()
    elif damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "corrupt":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    else:
        path.write_bytes(bytes(data) + b"\0")
    restored = make_buffer()
    Stream(1, seed=12).add([restored], 3)  # data the failed restore must not leave half overwritten
    with pytest.raises(
        CheckpointError,
        match={"missing": "is missing", "truncated": "truncated", "corrupt": "corrupt", "longer": "changed"}[damage],
    ) as info:
        ReplayStore(tmp_path).restore(restored, manifest)
    assert str(path) in str(info.value) and info.value.damaged
    assert isinstance(info.value, InputError)
    if damage == "corrupt":  # found while reading: the buffer is emptied, nothing half-restored is left as data
        assert restored.size() == 0 and not restored.frame_heads.any()
    else:  # found before reading: the buffer is unchanged
        assert restored.transitions_added == 3 and restored.resets == 0


def test_mismatched_buffer_or_manifest_is_a_clear_error(tmp_path):
    buffer = make_buffer(buffer_size=24)
    Stream(1, seed=7).add([buffer], 5)
    manifest = ReplayStore(tmp_path).save(buffer)
    with pytest.raises(CheckpointError, match="buffer_size is 24 in the checkpoint and 30 in this buffer"):
        ReplayStore(tmp_path).restore(make_buffer(buffer_size=30), manifest)
    with pytest.raises(CheckpointError, match="format"):
        ReplayStore(tmp_path).restore(make_buffer(), {**manifest, "format": "other/9"})
    broken = through_json(manifest)
    broken["chunks"][0]["bytes"] += 1
    with pytest.raises(CheckpointError, match="inconsistent"):
        ReplayStore(tmp_path).restore(make_buffer(), broken)
    for damage in (
        lambda m: m["chunks"][0].update(file="../../elsewhere.bin"),  # only chunk names of the folder are read
        lambda m: m["chunks"][0]["segments"][0].update(start=-4),
        lambda m: m["chunks"][0]["segments"][-1].update(env=5),
        lambda m: m["chunks"].append("chunk"),
        lambda m: m["state"].update(pos=2),  # disagrees with transitions_added
        lambda m: m["state"].pop("frame_heads"),
        lambda m: m.update(layout=[]),
    ):
        broken = through_json(manifest)
        damage(broken)
        with pytest.raises(CheckpointError, match="damaged|inconsistent"):
            ReplayStore(tmp_path).restore(make_buffer(), broken)
    buffer.pos = 3  # changed behind add(): what is new is unknown
    with pytest.raises(CheckpointError, match="transitions_added"):
        ReplayStore(tmp_path).save(buffer)
    with pytest.raises(InputError, match="max_file_bytes"):
        ReplayStore(tmp_path, max_file_bytes=0)
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="is a file"):
        ReplayStore(tmp_path / "file")


def test_full_disk_keeps_every_earlier_chunk(tmp_path, monkeypatch):
    """ENOSPC while writing the second file of a save: the save's files are deleted, earlier ones unchanged, the
    error names the folder, and the next save is still incremental to the last complete one."""
    buffer = make_buffer(buffer_size=40)
    stream = Stream(1, seed=8)
    store = ReplayStore(tmp_path, max_file_bytes=2000)
    stream.add([buffer], 12)
    first = store.save(buffer)
    before = {name: (tmp_path / name).read_bytes() for name in chunk_files(tmp_path)}
    heads = int(buffer.frame_heads[0])
    stream.add([buffer], 15)
    calls = []

    def full_disk(file, data):
        calls.append(len(data))
        if len(calls) > 7:  # the first file is complete by then
            raise OSError(errno.ENOSPC, "No space left on device")
        file.write(data)

    monkeypatch.setattr(replay_checkpoint, "_write", full_disk)
    with pytest.raises(OSError, match=str(tmp_path)) as info:
        store.save(buffer)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(tmp_path)
    assert {name: (tmp_path / name).read_bytes() for name in chunk_files(tmp_path)} == before
    assert sorted(os.listdir(tmp_path)) == sorted(before)  # no temporary file left either
    monkeypatch.undo()
    second = store.save(buffer)
    added = second["chunks"][len(first["chunks"]) :]
    assert sum(chunk["bytes"] for chunk in added) == new_bytes(buffer, 15, int(buffer.frame_heads[0]) - heads)
    restored = make_buffer(buffer_size=40)
    store.restore(restored, second)
    assert_same_state(buffer, restored)


def test_chunk_names_are_never_reused(tmp_path):
    """A new store on a folder numbers its chunks after the ones there (e.g. left by a save whose checkpoint was
    never written)."""
    buffer = make_buffer()
    Stream(1, seed=9).add([buffer], 10)
    first = ReplayStore(tmp_path).save(buffer)
    second = ReplayStore(tmp_path).save(buffer)  # another store: a full save, new names
    assert not {chunk["file"] for chunk in first["chunks"]} & {chunk["file"] for chunk in second["chunks"]}


@settings(max_examples=25, deadline=None)
@given(
    operations=st.lists(
        st.one_of(st.integers(1, 45), st.sampled_from(["save", "reset", "resume"])), min_size=1, max_size=12
    ),
    n_envs=st.sampled_from([1, 2]),
)
def test_any_sequence_of_adds_saves_resets_and_resumes(tmp_path_factory, operations, n_envs):
    """Whatever the order of adds, saves, resets and resumes, every save restores to the buffer it saved."""
    folder = tmp_path_factory.mktemp("replay")
    buffer = make_buffer(buffer_size=16, n_envs=n_envs)
    stream = Stream(n_envs, seed=len(operations))
    store = ReplayStore(folder, max_file_bytes=3000)
    reset_seen = False
    for operation in operations + ["save"]:
        if isinstance(operation, int):
            stream.add([buffer], operation)
        elif operation == "reset":
            buffer.reset()
            reset_seen = True
        else:
            manifest = through_json(store.save(buffer))
            store.collect_garbage(keep=[manifest])
            restored = make_buffer(buffer_size=16, n_envs=n_envs)
            if operation == "resume":  # go on from the restored buffer, with a new store
                store = ReplayStore(folder, max_file_bytes=3000)
                store.restore(restored, manifest)
                assert_same_state(buffer, restored, whole_arrays=not reset_seen)
                buffer, reset_seen = restored, False
            else:
                ReplayStore(folder).restore(restored, manifest)
                assert_same_state(buffer, restored, whole_arrays=not reset_seen)


KILLED_DURING_SAVE = """
import json, os, signal, sys
sys.path.insert(0, sys.argv[1])
from test_replay_checkpoint import Stream, make_buffer
from sb3_collapse.run import replay_checkpoint
from sb3_collapse.run.replay_checkpoint import ReplayStore

buffer, stream, store = make_buffer(buffer_size=40), Stream(1, seed=13), ReplayStore(sys.argv[2], max_file_bytes=2000)
stream.add([buffer], 12)
first = store.save(buffer)
with open(sys.argv[3], "w") as file:
    json.dump(first, file)
stream.add([buffer], 20)

def killed(file, data):
    file.write(data)
    if len([name for name in os.listdir(sys.argv[2]) if name.startswith("chunk-")]) > len(first["chunks"]):
        os.kill(os.getpid(), signal.SIGKILL)  # a file of this save complete, the next one half written

replay_checkpoint._write = killed
store.save(buffer)
"""


def test_sigkill_during_a_save_leaves_the_previous_checkpoint_whole(tmp_path):
    folder, manifest_path = tmp_path / "replay", tmp_path / "manifest.json"
    child = subprocess.run(
        [sys.executable, "-c", KILLED_DURING_SAVE, os.path.dirname(__file__), str(folder), str(manifest_path)],
        check=False,
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=120,
    )
    assert child.returncode == -9, child.stderr
    manifest = json.loads(manifest_path.read_text())
    leftovers = set(os.listdir(folder)) - listed(manifest)
    assert any(name.endswith(replay_checkpoint.TEMP_SUFFIX) for name in leftovers)  # killed mid-write
    assert any(name.startswith(replay_checkpoint.CHUNK_PREFIX) for name in leftovers)  # complete, never listed
    buffer = make_buffer(buffer_size=40)
    Stream(1, seed=13).add([buffer], 12)
    restored = make_buffer(buffer_size=40)
    store = ReplayStore(folder)
    store.restore(restored, manifest)
    assert_same_state(buffer, restored)
    store.collect_garbage(keep=[manifest])
    assert set(os.listdir(folder)) == listed(manifest)
