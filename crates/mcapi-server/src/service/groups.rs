//! Session groups (docs/groups.md): N sessions of one model and one agent
//! configuration, created in one call on one shard, and stepped together
//! by columns (`StepGroup`, `POST /v1/groups/{id}/steps`). Each member is an
//! ordinary session; the group is its list of members, kept in memory and
//! rebuilt at start from the members' creation records, each of which names
//! its group ([`GroupTag`](super::membership::GroupTag)).
//!
//! What a step carries is [`Columns`], checked here against the group's
//! shape ([`Group::observations`]) before anything is applied, so both
//! transports refuse the same message with the same code: a mask that is
//! not strictly increasing or names a member beyond the group
//! (`invalid_mask`), a column whose length disagrees with the members
//! stepped, the stimulus dimensions or the observation dimensions
//! (`column_length`; `seqs` too), a number no member could take (a state
//! outside the model, a NaN, infinite or too large stimulus component, a NaN
//! observation coordinate: the code one such observation gets alone). What
//! only a member's own state refuses (an action it cannot take, a stimulus
//! on its first observation, a member deleted alone, a seq the member's
//! session refuses) refuses that member only, with the code an `Interact` of
//! the same observation would end with. With `seqs`, each member's
//! observation carries its seq and is checked by its session as a lone
//! numbered observation is: one already applied is answered with its
//! recorded step (`replayed`) and applied nothing.

use std::sync::{Arc, Weak};

use parking_lot::Mutex;
use serde::{Deserialize, Serialize};

use mcapi_core::AlgoError;
use mcapi_core::spec::ActionRef;

use super::agent_config::{SessionConfig, UpdateMode};
use super::error::ServiceError;
use super::session::{Owner, Session, SessionRef};
use super::table::{Entry, SessionTable};
use super::wire::{ModelSummary, ObservationIn};

/// In a step's `action_taken` column: the member took the advised action.
pub const ADVISED: u32 = u32::MAX;

/// SplitMix64's increment (the golden ratio in 64 bits).
const GOLDEN_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output function of the state `z` (after its increment).
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The seed of member `index` of a group seeded `seed` (docs/groups.md,
/// "Seeds"): output number `index` (from 0) of a SplitMix64 generator
/// started at `seed`, that is `mix(seed + (index + 1) · 0x9E3779B97F4A7C15)`
/// in wrapping 64-bit arithmetic, with SplitMix64's output function `mix`.
pub fn member_seed(seed: u64, index: u64) -> u64 {
    mix(seed.wrapping_add(index.wrapping_add(1).wrapping_mul(GOLDEN_GAMMA)))
}

/// A request to create a group (`POST /v1/groups`): a session's body, the
/// number of members and the group's seed.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateGroup {
    /// The environment model of every member, as `POST /v1/sessions` takes it.
    #[schema(value_type = Object)]
    pub model: serde_json::Value,
    /// The agent configuration of every member (without `seed`).
    #[serde(default)]
    pub agent: SessionConfig,
    /// Members, 1 to `--max-group-members`.
    pub n: u64,
    /// The group's seed; drawn when absent.
    #[serde(default)]
    pub seed: Option<u64>,
}

/// A group in memory.
#[derive(Debug)]
pub struct Group {
    /// `s<shard>.g<ULID>`: the shard of every member.
    pub id: String,
    /// The key that created it.
    pub owner: Owner,
    /// The seed member seeds derive from ([`member_seed`]).
    pub seed: u64,
    /// The members by index; `None` for one the store could not rebuild at
    /// start (skipped, docs/sessions.md, "Durability and recovery").
    pub members: Vec<Option<String>>,
    /// The members' model.
    pub model: Arc<ModelSummary>,
    /// The members' update mode.
    pub mode: UpdateMode,
    /// One member's estimated CPU time per observation (they share their
    /// model and configuration).
    pub tick_us: u64,
    /// Where each member was last found in the session table, and the
    /// table's generation then ([`Resolved`]).
    pub resolved: Resolved,
}

/// Each member's session as a group step last found it in the session
/// table, with the table's generation at that lookup
/// ([`super::table::SessionTable::generation`]). While the generation is
/// unchanged, the table still maps the member's id to that entry, so a step
/// takes the member from here instead of searching the table's ordered map
/// of string ids (a search touches a dozen cold nodes per member; BENCHMARKS.md,
/// "Vectorised stepping"). Weak, so an eviction's count of who holds a
/// session is unchanged and a member that leaves memory is freed: all but
/// its session's own struct (about 1.4 KiB), which a weak reference keeps
/// allocated until it is dropped; an eviction drops its member's
/// ([`Resolved::forget`]), the next step of the group drops a deleted
/// member's.
#[derive(Debug, Default)]
pub struct Resolved(Mutex<Vec<(u64, Weak<Session>)>>);

impl Resolved {
    /// The resident session of member `index` of `members` in `table` (read
    /// under its lock by the caller), from what is remembered if `table`'s
    /// generation is the one it was found with, else looked up and
    /// remembered.
    pub fn resident(
        slots: &mut Vec<(u64, Weak<Session>)>,
        table: &SessionTable,
        members: &[Option<String>],
        index: usize,
    ) -> Option<SessionRef> {
        let generation = table.generation();
        if slots.len() != members.len() {
            slots.clear();
            slots.resize(members.len(), (0, Weak::new()));
        }
        let slot = slots.get_mut(index)?;
        if slot.0 == generation {
            return slot.1.upgrade();
        }
        let found = members
            .get(index)?
            .as_deref()
            .and_then(|id| table.get(id))
            .and_then(Entry::resident)
            .cloned();
        *slot = (
            generation,
            found.as_ref().map_or_else(Weak::new, Arc::downgrade),
        );
        found
    }

    /// Forgets where member `index` was found (it left memory).
    pub fn forget(&self, index: usize) {
        if let Some(slot) = self.0.lock().get_mut(index) {
            *slot = (0, Weak::new());
        }
    }

    /// The slots, locked.
    pub fn lock(&self) -> parking_lot::MutexGuard<'_, Vec<(u64, Weak<Session>)>> {
        self.0.lock()
    }
}

/// A group as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GroupInfo {
    /// `s<shard>.g<ULID>`.
    pub id: String,
    /// Members (N).
    pub size: usize,
    /// The group's seed; member i's seed is derived from it (docs/groups.md).
    pub seed: u64,
    /// The members' update mode.
    pub update_mode: UpdateMode,
    /// Stimulus dimensions of the model (n): the width of the `stimuli` and
    /// `drives` columns.
    pub stimuli: usize,
    /// For a continuous model: the observation's dimensions (d).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation_dim: Option<usize>,
    /// The member session ids by index; `null` for a member the store
    /// could not rebuild at start.
    pub members: Vec<Option<String>>,
}

impl Group {
    /// The API's view.
    pub fn info(&self) -> GroupInfo {
        GroupInfo {
            id: self.id.clone(),
            size: self.members.len(),
            seed: self.seed,
            update_mode: self.mode,
            stimuli: self.model.stimuli.len(),
            observation_dim: self.dim(),
            members: self.members.clone(),
        }
    }

    /// The observation dimensions of a continuous model.
    pub fn dim(&self) -> Option<usize> {
        self.model
            .continuous
            .as_ref()
            .map(|c| c.observation_space.low.len())
    }

    /// The members a step's columns are for and their observations, one per
    /// member stepped, in mask order; refused whole (nothing applied) when
    /// the columns do not fit the group.
    pub fn observations(
        &self,
        columns: Columns,
    ) -> Result<Vec<(usize, ObservationIn)>, ServiceError> {
        let Columns {
            mask,
            states,
            observations,
            stimuli,
            action_taken,
            seqs,
        } = columns;
        let size = self.members.len();
        let stepped: Vec<usize> = if mask.is_empty() {
            (0..size).collect()
        } else {
            check_mask(&mask, size)?
        };
        let m = stepped.len();
        let n = self.model.stimuli.len();
        let column = |name: &str, got: usize, want: usize, what: &str| {
            if got == want {
                Ok(())
            } else {
                Err(ServiceError::ColumnLength(format!(
                    "`{name}` has {got} entries; {want} expected ({what})"
                )))
            }
        };
        let members = format!("one per member stepped: {m}");
        match self.dim() {
            Some(d) => {
                column(
                    "observations",
                    observations.len(),
                    m.saturating_mul(d),
                    &format!("{m} members stepped x {d} dimensions"),
                )?;
                if !states.is_empty() {
                    return Err(ServiceError::ColumnLength(format!(
                        "`states` has {} entries; a continuous model takes `observations` \
                         ({m} x {d} numbers), no states",
                        states.len()
                    )));
                }
            }
            None => {
                column("states", states.len(), m, &members)?;
                if !observations.is_empty() {
                    return Err(ServiceError::ColumnLength(format!(
                        "`observations` has {} entries; this group's model has numbered \
                         states: send `states`",
                        observations.len()
                    )));
                }
            }
        }
        if !stimuli.is_empty() {
            column(
                "stimuli",
                stimuli.len(),
                m.saturating_mul(n),
                &format!("{m} members stepped x {n} stimulus dimensions, or none on a first step"),
            )?;
        }
        if !action_taken.is_empty() {
            column("action_taken", action_taken.len(), m, &members)?;
        }
        if !seqs.is_empty() {
            column("seqs", seqs.len(), m, &members)?;
        }
        self.check_values(&states, &observations, &stimuli)?;
        let d = self.dim().unwrap_or(0);
        let out = stepped
            .into_iter()
            .enumerate()
            .map(|(j, member)| {
                let obs = ObservationIn {
                    state: states.get(j).map(|&s| s as usize),
                    observation: (d > 0).then(|| observations[j * d..(j + 1) * d].to_vec()),
                    stimulus: (!stimuli.is_empty()).then(|| stimuli[j * n..(j + 1) * n].to_vec()),
                    action_taken: action_taken
                        .get(j)
                        .filter(|&&a| a != ADVISED)
                        .map(|&a| ActionRef::Index(a as usize)),
                    signal: None,
                    signal_source: None,
                    seq: seqs.get(j).copied(),
                };
                (member, obs)
            })
            .collect();
        Ok(out)
    }
}

impl Group {
    /// The numbers of a step that no member could take, refused with the
    /// message: a state outside the model, a stimulus component that is
    /// NaN, infinite or beyond ±10¹², an observation coordinate that is NaN
    /// or infinite. Each gets the code one such observation sent alone gets.
    fn check_values(
        &self,
        states: &[u32],
        observations: &[f64],
        stimuli: &[f64],
    ) -> Result<(), ServiceError> {
        let states_of_model = self.model.states;
        if self.dim().is_none()
            && let Some(&state) = states.iter().find(|&&s| s as usize >= states_of_model)
        {
            return Err(AlgoError::StateOutOfRange {
                state: state as usize,
                states: states_of_model,
            }
            .into());
        }
        let n = self.model.stimuli.len();
        if n > 0 {
            for row in stimuli.chunks_exact(n) {
                mcapi_core::error::check_stimulus(row, n)?;
            }
        }
        if let Some(j) = observations.iter().position(|x| !x.is_finite()) {
            return Err(AlgoError::InvalidObservation(format!(
                "`observations` has a NaN or infinite coordinate (number {j})"
            ))
            .into());
        }
        Ok(())
    }
}

/// The member indices of a mask: strictly increasing, each below `size`.
fn check_mask(mask: &[u32], size: usize) -> Result<Vec<usize>, ServiceError> {
    let mut out = Vec::with_capacity(mask.len().min(size));
    for (j, &i) in mask.iter().enumerate() {
        let i = i as usize;
        if i >= size {
            return Err(ServiceError::InvalidMask(format!(
                "`mask[{j}]` is {i}; the group's members are 0..{size}"
            )));
        }
        if let Some(&before) = out.last()
            && i <= before
        {
            let why = if i == before {
                "repeats the entry before it"
            } else {
                "is below the entry before it"
            };
            return Err(ServiceError::InvalidMask(format!(
                "`mask[{j}]` is {i} and {why} ({before}): member indices are strictly increasing"
            )));
        }
        out.push(i);
    }
    Ok(out)
}

/// One step of a group by columns, as both transports decode it (the
/// layout of docs/groups.md, "Stepping"). Every column of M entries has one
/// per member stepped, in mask order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Columns {
    /// The members stepped, strictly increasing; empty: all of them.
    pub mask: Vec<u32>,
    /// The state each is in (models with numbered states): M entries.
    pub states: Vec<u32>,
    /// A continuous model's observations, row-major: M × d numbers.
    pub observations: Vec<f64>,
    /// The stimuli received on arrival, row-major: M × n numbers, or none
    /// (the members' first step).
    pub stimuli: Vec<f64>,
    /// The action each took, [`ADVISED`] for the advised one: M entries, or
    /// none (every member took its advised action).
    pub action_taken: Vec<u32>,
    /// Each member's observation's seq (docs/sessions.md, "Delivery
    /// guarantees"): M entries, or none (applied as they come, at least
    /// once).
    pub seqs: Vec<u64>,
}

/// What one step answers for one member: its step, or why it was refused
/// (the member's observation was not applied, unless the code is
/// `numerical_failure`).
#[derive(Debug)]
pub struct MemberStep {
    /// The member's index in the group.
    pub index: usize,
    /// Its step or its refusal.
    pub result: Result<super::wire::StepOut, ServiceError>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn member_seeds_are_the_outputs_of_splitmix64_from_the_group_seed() {
        // The reference sequence of SplitMix64 seeded with 1234567
        // (Vigna's splitmix64.c): its first outputs.
        let mut state: u64 = 1_234_567;
        let mut next = || {
            state = state.wrapping_add(GOLDEN_GAMMA);
            mix(state)
        };
        for i in 0..5 {
            assert_eq!(member_seed(1_234_567, i), next());
        }
        assert_eq!(member_seed(1_234_567, 0), 6_457_827_717_110_365_317);
        assert_ne!(member_seed(7, 0), member_seed(7, 1));
    }

    #[test]
    fn a_mask_is_strictly_increasing_and_within_the_group() {
        assert_eq!(check_mask(&[0, 2, 5], 6).expect("fine"), vec![0, 2, 5]);
        let e = check_mask(&[0, 2, 2], 6).expect_err("duplicate");
        assert!(e.to_string().contains("repeats"), "{e}");
        let e = check_mask(&[3, 1], 6).expect_err("decreasing");
        assert!(e.to_string().contains("below"), "{e}");
        let e = check_mask(&[6], 6).expect_err("out of range");
        assert!(e.to_string().contains("0..6"), "{e}");
    }
}
