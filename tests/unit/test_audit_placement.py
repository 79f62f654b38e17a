"""Where the audit puts a rotated copy: the translation that keeps its contact where the recording
had it (pure; no simulator)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.augmenter.audit_placement import anchor_shift
from services.augmenter.core.isometric import isometric_copy
from tests.helpers.synthetic import synthetic_episode

pytestmark = pytest.mark.unit


def test_the_anchor_turns_a_copy_about_its_contact_steps():
    """Shifted by ``anchor_shift``, the turned copy's contact steps sit where the recording had
    them on average (their centroid is the turn's fixed point); with no contact, its last step."""
    demo, _ = synthetic_episode(3)
    contacts = np.zeros_like(demo.contacts)
    contacts[-6:-2, 1] = True
    demo = dataclasses.replace(demo, contacts=contacts)
    for phi in (0.3, 2.0):
        copy = isometric_copy(demo, phi, seed=0, copy_index=0, episode_id="x")
        turned = np.asarray(copy.gripper_pose[:, :2], np.float64) + anchor_shift(copy)
        src = np.asarray(demo.gripper_pose[:, :2], np.float64)
        touching = contacts.any(axis=1)
        np.testing.assert_allclose(turned[touching].mean(0), src[touching].mean(0), atol=1e-5)
        assert np.abs(turned[touching] - src[touching]).max() > 1e-3  # turned, not merely copied
    free = dataclasses.replace(demo, contacts=np.zeros_like(contacts))
    copy = isometric_copy(free, 1.0, seed=0, copy_index=0, episode_id="x")
    np.testing.assert_allclose(
        copy.gripper_pose[-1, :2] + anchor_shift(copy), demo.gripper_pose[-1, :2], atol=1e-5
    )
    assert np.allclose(anchor_shift(demo), 0.0)  # not a rotated copy: nothing to undo
