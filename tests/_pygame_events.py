"""Scripted pygame input for the human-mentor tests: post key and joystick-axis events (headless)."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import pygame  # noqa: E402


def key(k, down=True):
    """Post a KEYDOWN (or KEYUP) event for pygame key ``k``."""
    pygame.event.post(pygame.event.Event(pygame.KEYDOWN if down else pygame.KEYUP, key=k))


def axis(a, v, iid=0):
    """Post a JOYAXISMOTION event: axis ``a`` of joystick ``iid`` at value ``v``."""
    pygame.event.post(pygame.event.Event(pygame.JOYAXISMOTION, instance_id=iid, axis=a, value=v))
