"""A pygame window that shows the frames of an env rendered in ``"human"`` mode."""

from __future__ import annotations

import numpy as np


class PygameWindow:
    """Opens on the first frame; shows ``(height, width, 3)`` uint8 images at ``fps`` frames per second.

    :param title: window caption.
    :param fps: frames per second.
    """

    def __init__(self, title: str, fps: int) -> None:
        import pygame

        self._pygame = pygame
        self.title = title
        self.fps = fps
        self._surface = None
        self._clock = None

    def show(self, image: np.ndarray) -> None:
        """Display ``image`` ``(height, width, 3)`` uint8 (row 0 at the top)."""
        pygame = self._pygame
        if self._surface is None:
            pygame.init()
            self._surface = pygame.display.set_mode((image.shape[1], image.shape[0]))
            pygame.display.set_caption(self.title)
            self._clock = pygame.time.Clock()
        pygame.event.pump()
        self._surface.blit(pygame.surfarray.make_surface(image.swapaxes(0, 1)), (0, 0))
        pygame.display.flip()
        self._clock.tick(self.fps)

    def close(self) -> None:
        """Close the window if it was opened."""
        if self._surface is not None:
            self._pygame.display.quit()
            self._pygame.quit()
            self._surface = None
            self._clock = None
