//! PLACEHOLDER being replaced by the lane-parallel walk.
use super::medium::{Medium, Source};
use super::tally::{ProfileTally, RadialBins};
pub fn simulate_lanes(
    medium: &Medium,
    source: &Source,
    bins: &RadialBins,
    max_events: u32,
    seed: u64,
    first: u64,
    count: u64,
) -> ProfileTally {
    super::walk::simulate_scalar(medium, source, bins, max_events, seed, first, count)
}
