//! What a member session knows of its group: the tag its creation record
//! carries ([`GroupTag`]) and its place among the members ([`spread`]),
//! which staggers the work members stepped together would otherwise all do
//! at once. The session, its records and its history ring need these; the
//! groups themselves (`groups.rs`) build on the sessions.

use serde::{Deserialize, Serialize};

/// What a member's creation record says of its group (the `group` of
/// `durable::SessionRecord`): enough to rebuild the group's member list at
/// start from its members alone.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct GroupTag {
    /// The group's id.
    pub group: String,
    /// The member's index, `0..size`.
    pub index: u32,
    /// Members of the group.
    pub size: u32,
    /// The group's seed.
    pub seed: u64,
}

/// Member `index`'s place in `0..span`, the members of a group of `size`
/// spread evenly over it: index × span / size (an index past the group
/// counts as its last). What staggers the work that members stepped
/// together would otherwise all do at the same step: their snapshots and
/// their history rings' doublings.
pub fn spread(index: u32, size: u32, span: u64) -> u64 {
    let size = size.max(1);
    let place = u128::from(index.min(size - 1)) * u128::from(span) / u128::from(size);
    // Below `span`, so it fits.
    u64::try_from(place).unwrap_or(0)
}
