"""TensorBoard runs named after the algorithm, for every sb3_hgrn algorithm."""

from __future__ import annotations

from typing import Any

from stable_baselines3.common.type_aliases import MaybeCallback


class AlgorithmNamedRuns:
    """Mixin before an SB3 algorithm class: ``learn`` names the TensorBoard run after the algorithm's
    class (``SoftDQN_1``, ``SACHGRN_1``, ...) unless ``tb_log_name`` is given."""

    def learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> Any:
        """SB3's ``learn``; the TensorBoard run is named after the algorithm unless ``tb_log_name``
        is given."""
        tb_log_name = tb_log_name or type(self).__name__
        return super().learn(  # type: ignore[misc]
            total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar
        )
