"""`Scene.preallocate` of more voxels than a scene can hold, or than the system will give memory for:
a ValueError naming ``voxels`` (never a MemoryError), the scene unchanged."""

from __future__ import annotations

import pytest

from canonical_core import SceneConfig
from canonical_core.config import MAX_VOXELS
from canonical_core.datasets import synthetic_rgbd
from canonical_core.scene import Scene
from canonical_core.scene.voxel_map import VoxelMap


def test_a_preallocation_beyond_the_most_a_scene_holds_is_refused():
    scene = Scene(SceneConfig(voxel_size=0.02), initial_capacity=16)  # no max_voxels: the library's own bound
    capacity, memory = scene.capacity, scene.memory_bytes()
    with pytest.raises(ValueError, match=rf"^voxels: 1000000000000 is above the most a scene holds \({MAX_VOXELS}\)"):
        scene.preallocate(10**12)
    assert scene.capacity == capacity and scene.memory_bytes() == memory


def test_a_preallocation_the_system_refuses_names_the_memory_it_asked_for(monkeypatch):
    frame = synthetic_rgbd(num_frames=1, width=64, height=48)[0]
    scene, plain = Scene(SceneConfig(voxel_size=0.02), initial_capacity=16), Scene(SceneConfig(voxel_size=0.02))
    capacity, memory = scene.capacity, scene.memory_bytes()

    def refused(self, capacity, rows, names=None):  # what a machine without that much memory answers
        raise MemoryError

    with monkeypatch.context() as patch:
        patch.setattr(VoxelMap, "_reserve", refused)
        with pytest.raises(ValueError, match=r"^voxels: 100000000 voxels ask for about [\d.]+ GiB, more memory than"):
            scene.preallocate(100_000_000)  # beyond the rows reserved up front
    assert scene.capacity == capacity and scene.memory_bytes() == memory
    scene.fold(frame)
    plain.fold(frame)
    assert scene.digest() == plain.digest()


@pytest.mark.parametrize("bad", [-1, 1.5, "a", True, 2**40])
def test_a_scene_takes_only_a_whole_number_of_voxels_as_its_initial_capacity(bad):
    """-1 once gave a capacity of 2^24 - 1, 2^40 a MemoryError, a string a TypeError."""
    with pytest.raises(ValueError, match=r"^initial_capacity: expected a whole number of voxels in \[0, "):
        Scene(SceneConfig(voxel_size=0.01), initial_capacity=bad)
    assert Scene(SceneConfig(voxel_size=0.01), initial_capacity=0).capacity >= 0
