"""What the sonde tracker took in, and what it refused or could not use (counted, not hidden)."""
from __future__ import annotations

from dataclasses import dataclass, fields

__all__ = ["TrackerCounters"]


@dataclass
class TrackerCounters:
    """What the tracker took in, and what it refused or could not use (counted, not hidden)."""

    messages: int = 0  # bus messages handed to on_message
    ignored: int = 0  # other runs, kinds or sondes this tracker does not follow, other radars
    duplicates: int = 0  # (source, seq) seen before
    stale: int = 0  # older than (or at) the sonde's filter time (lag_window_s = 0)
    late_accepted: int = 0  # out of sequence, within the lag window: used by re-processing
    too_late: int = 0  # out of sequence, older than the lag window: dropped
    reprocess_runs: int = 0  # steps that went back to re-run epochs completed by late messages
    reprocessed_epochs: int = 0  # steps re-run (their Estimates are not published again)
    superseded: int = 0  # a second message of the same kind, sonde and epoch (the later wins)
    epochs: int = 0  # sonde-epochs processed
    relay_updates: int = 0
    relay_empty: int = 0  # relay epochs with no satellite (GNSS outage, out of range)
    relay_gated: int = 0  # relay blocks rejected at the chi-square gate
    relay_manoeuvre: int = 0  # relay blocks accepted only under the manoeuvre hypothesis
    radar_updates: int = 0
    range_only_updates: int = 0  # angles_valid False: range row only
    radar_gated: int = 0
    radar_manoeuvre: int = 0
    init_radar: int = 0
    init_relay: int = 0
    init_waiting: int = 0  # epochs of a sonde that could not initialise it
    reacquired: int = 0  # tracks re-initialised after reacquire_after rejections in a row
    landings: int = 0  # tracks that reached the ground descending (relaxed kinematics, landing): at rest since
    lost: int = 0  # tracks declared lost: no accepted measurement for max_coast_s (no Estimate until re-initialised)
    window_manoeuvre: int = 0  # manoeuvres found by the sliding-window NIS test
    ukf_updates: int = 0  # sonde-epochs updated by the UKF (filter "ukf", or "auto" when needed)
    bias_assigned: int = 0  # satellites given a (fresh) error state
    bias_overflow: int = 0  # satellite-epochs with no free error state (their error taken as white)
    estimates: int = 0
    integrity_epochs: int = 0  # epochs judged by the integrity monitor (params.integrity)
    integrity_rows_left_out: int = 0  # measurement rows the monitor kept out of an update (jump or excluded channel)
    integrity_exclusions: int = 0  # channels excluded (a step that stays, or a drift)
    integrity_readmissions: int = 0
    integrity_events: int = 0  # IntegrityEvents built (and published when attached)
    integrity_unmonitored: int = 0  # satellite-epochs with no free monitor channel (used unjudged)
    integrity_common_mode: int = 0  # sonde-epochs not judged: jumps on most rows at once (a manoeuvre, not a channel)
    integrity_warmup: int = 0  # sonde-epochs not judged: the track was (re)initialised less than the warm-up ago

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}
