//! Session groups (docs/groups.md): N sessions of one model and one agent
//! configuration created on one shard in one call, priced and counted
//! whole; read, deleted and stepped by columns. A step applies each
//! member's observation as [`SessionManager::observe`] applies one alone
//! (the same checks, update and log entry): the cheap members in chunks on
//! the blocking pool, the others through `observe` itself. With a store,
//! the cheap members' log entries go into one [`Batch`] per chunk: a write
//! of the log (and a commit) per chunk, not per member, expanded into each
//! member's own log by the store's checkpoint (so each member recovers,
//! moves with its shard and is read as any session); made durable before
//! the reply.

use std::collections::BTreeMap;

use futures_util::future::join_all;
use mcapi_store::Sent;

use super::*;
use crate::service::groups::{
    Columns, CreateGroup, Group, GroupInfo, MemberStep, Resolved, member_seed,
};
use crate::service::membership::GroupTag;

/// The groups in memory by id.
pub(crate) type GroupTable = BTreeMap<String, Arc<Group>>;

/// One member of a group as recovered or imported: what its group is
/// rebuilt from.
pub(super) struct GroupMember {
    tag: GroupTag,
    id: String,
    model: Arc<ModelSummary>,
    mode: UpdateMode,
    owner: session::Owner,
    tick_us: u64,
}

impl GroupMember {
    /// The member `session` is, if it was created in a group.
    pub(super) fn of(session: &Session) -> Option<Self> {
        let tag = session.group.clone()?;
        Some(Self {
            tag,
            id: session.id.clone(),
            model: Arc::clone(&session.model),
            mode: session.mode,
            owner: session.owner,
            tick_us: cost::estimate(&session.model, &session.config).tick_us,
        })
    }
}

/// A group's creation as [`SessionManager::create_group_from`] takes it:
/// the model parsed (and its text, for the store), the members'
/// configuration, how many, and the group's seed.
struct GroupRequest<'a> {
    input: ModelInput,
    model_text: Option<String>,
    agent: &'a SessionConfig,
    n: u64,
    seed: Option<u64>,
}

impl SessionManager {
    /// Creates a group from REST's body (the model as JSON, parsed as
    /// `POST /v1/sessions` parses it); see [`Self::create_group_parsed`].
    pub fn create_group(
        &self,
        caller: Caller,
        req: CreateGroup,
    ) -> Result<GroupInfo, ServiceError> {
        self.create_group_watched(caller, req, &Watch::default())
    }

    /// [`Self::create_group`] for a request that may be abandoned: the
    /// model's build and the members' stop once `watch` says so.
    pub fn create_group_watched(
        &self,
        caller: Caller,
        req: CreateGroup,
        watch: &Watch,
    ) -> Result<GroupInfo, ServiceError> {
        let CreateGroup {
            model,
            agent,
            n,
            seed,
        } = req;
        let model_text = self.durability.as_ref().map(|_| model.to_string());
        let input = ModelInput::parse(model)?;
        let req = GroupRequest {
            input,
            model_text,
            agent: &agent,
            n,
            seed,
        };
        self.create_group_from(caller, req, watch)
    }

    /// Creates a group from a model already parsed (gRPC's typed `Model`);
    /// otherwise as [`Self::create_group`].
    pub fn create_group_parsed(
        &self,
        caller: Caller,
        input: ModelInput,
        agent: &SessionConfig,
        n: u64,
        seed: Option<u64>,
        watch: &Watch,
    ) -> Result<GroupInfo, ServiceError> {
        let model_text = match &self.durability {
            Some(_) => Some(input.to_json_text()?),
            None => None,
        };
        let req = GroupRequest {
            input,
            model_text,
            agent,
            n,
            seed,
        };
        self.create_group_from(caller, req, watch)
    }

    /// Creates a group of `n` sessions of one model and configuration
    /// (docs/groups.md, "Creating a group"): member i is seeded
    /// [`member_seed`]`(seed, i)`, every member is on the group's shard. The
    /// whole group is checked against the limits, the per-session budgets
    /// and the caller's quota before any member is built, and refused whole;
    /// with a store, the members' records are committed together before
    /// any is served. Synchronous and possibly slow: call it off the runtime.
    fn create_group_from(
        &self,
        caller: Caller,
        req: GroupRequest<'_>,
        watch: &Watch,
    ) -> Result<GroupInfo, ServiceError> {
        let GroupRequest {
            input,
            model_text,
            agent,
            n,
            seed,
        } = req;
        let n = usize::try_from(n).unwrap_or(usize::MAX);
        if n == 0 {
            return Err(ServiceError::field("n", "must be at least 1"));
        }
        if n > self.limits.max_group_members {
            return Err(ServiceError::LimitExceeded(format!(
                "`n` is {n}; the limit is {} members per group (--max-group-members)",
                self.limits.max_group_members
            )));
        }
        if agent.seed.is_some() {
            return Err(ServiceError::field(
                "agent.seed",
                "is not taken by a group: its members' seeds derive from the group's `seed`",
            ));
        }
        if agent.curiosity.is_some() {
            return Err(ServiceError::field(
                "agent.curiosity",
                "is not taken by a group: a group step has no column for curiosity signals",
            ));
        }
        let owner = caller.owner();
        let refused_for_count = |sessions: &SessionTable| {
            if sessions.len().saturating_add(n) > self.limits.max_sessions {
                return Some(ServiceError::TooManySessions(self.limits.max_sessions));
            }
            let held = sessions.usage(&owner).sessions;
            if held.saturating_add(n) > self.limits.max_key_sessions {
                return Some(ServiceError::QuotaExceeded(format!(
                    "this API key holds {held} sessions; a group of {n} would take it beyond \
                     its quota of {} (--max-key-sessions)",
                    self.limits.max_key_sessions
                )));
            }
            None
        };
        if let Some(e) = refused_for_count(&self.sessions.read()) {
            return Err(e);
        }
        let seed = seed.unwrap_or_else(|| self.setup.fresh_u64());
        let member_config = |i: usize| SessionConfig {
            seed: Some(member_seed(seed, i as u64)),
            ..agent.clone()
        };
        // One member first: its cost prices the group before the others
        // are built.
        let admit = |cost: &SessionCost| self.admit_cost(&owner, cost);
        let new = super::super::setup::NewBuild {
            admit: &admit,
            abandoned: Some(watch.flag()),
        };
        let first = self
            .setup
            .build_new(&input, &member_config(0), &self.limits, &new)?;
        let cost = cost::estimate(&first.1, &first.2);
        let total = SessionCost {
            bytes: cost.bytes.saturating_mul(n as u64),
            tick_us: cost.tick_us,
        };
        self.admit_cost(&owner, &cost)?;
        self.check_group_bytes(&total, &owner, n)?;
        let mut built = Vec::with_capacity(n);
        built.push(first);
        for i in 1..n {
            if watch.is_abandoned() {
                return Err(ServiceError::Unavailable(
                    "the request was abandoned while its members were built".into(),
                ));
            }
            built.push(self.setup.build(&input, &member_config(i), &self.limits)?);
        }
        let (shard, _guard) = match &self.placement {
            Some(p) => {
                let guard = p.mint(self.setup.fresh_u64()).ok_or_else(|| {
                    ServiceError::Unavailable(format!(
                        "replica `{}` owns no shard open for new sessions right now; retry (the router sends creates to every replica in turn)",
                        p.replica()
                    ))
                })?;
                (guard.shard(), Some(guard))
            }
            None => ((self.setup.fresh_u64() % SHARDS) as u16, None),
        };
        let group_id = format!("s{shard:04x}.g{}", ulid::Ulid::new());
        let ids: Vec<String> = (0..n)
            .map(|_| format!("s{shard:04x}.{}", ulid::Ulid::new()))
            .collect();
        let tag = |i: usize| GroupTag {
            group: group_id.clone(),
            index: i as u32,
            size: n as u32,
            seed,
        };
        if let (Some(d), Some(model)) = (&self.durability, model_text) {
            let writes = ids
                .iter()
                .zip(&built)
                .enumerate()
                .map(|(i, (id, (_, _, config)))| {
                    let record = durable::SessionRecord {
                        model: model.clone(),
                        config: config.clone(),
                        owner,
                        group: Some(tag(i)),
                    };
                    let bytes = serde_json::to_vec(&record).map_err(|e| {
                        ServiceError::Internal(format!("encoding a session record: {e}"))
                    })?;
                    Ok(Write::Session {
                        id: Arc::from(id.as_str()),
                        record: bytes,
                    })
                })
                .collect::<Result<Vec<_>, ServiceError>>()?;
            d.store
                .submit(writes)
                .wait_blocking()
                .map_err(ServiceError::from)?;
        }
        let model = Arc::clone(&built[0].1);
        let mode = built[0].2.update_mode;
        let sessions: Vec<SessionRef> = ids
            .iter()
            .zip(built)
            .enumerate()
            .map(|(i, (id, (learner, summary, config)))| {
                Arc::new(Session::resume(
                    id.clone(),
                    learner,
                    summary,
                    config,
                    self.durability.clone(),
                    session::Resumed {
                        owner,
                        group: Some(tag(i)),
                        pristine: true,
                        ..session::Resumed::default()
                    },
                ))
            })
            .collect();
        let group = Arc::new(Group {
            id: group_id.clone(),
            owner,
            seed,
            members: ids.iter().cloned().map(Some).collect(),
            model,
            mode,
            tick_us: cost.tick_us,
            resolved: Resolved::default(),
        });
        // Checked again under the lock: concurrent creates see each other
        // (room made again, a few times at most, for one that took it).
        let mut passes = 0;
        loop {
            let mut table = self.sessions.write();
            let refused = refused_for_count(&table).or_else(|| {
                let held = table.usage(&owner);
                let total_bytes = held.bytes.saturating_add(total.bytes);
                (total_bytes > self.limits.max_key_bytes).then(|| {
                    ServiceError::QuotaExceeded(format!(
                        "this API key's sessions would hold an estimated {total_bytes} bytes \
                         ({} now, {} for the group's {n} members); its quota is {} \
                         (--max-key-bytes)",
                        held.bytes, total.bytes, self.limits.max_key_bytes
                    ))
                })
            });
            let Some(e) = refused else {
                for session in &sessions {
                    table.insert(session.id.clone(), Arc::clone(session));
                }
                metrics::gauge!("mcapi_sessions").set(table.len() as f64);
                // Under the session table's lock: a shard move removing
                // this shard's sessions sees the group with them.
                self.groups
                    .write()
                    .insert(group_id.clone(), Arc::clone(&group));
                break;
            };
            drop(table);
            if matches!(e, ServiceError::QuotaExceeded(_))
                && passes < super::create::ROOM_PASSES
                && self.room_or_progress(&owner, total.bytes)
            {
                passes += 1;
                continue;
            }
            // Undo the stored records; the client sees the limit.
            let commits: Vec<_> = sessions.iter().filter_map(|s| s.delete()).collect();
            for commit in commits {
                let _ = commit.wait_blocking();
            }
            return Err(e);
        }
        tracing::info!(group = %group_id, members = n, "group created");
        Ok(group.info())
    }

    /// The group's estimated memory, all members together, against what
    /// the caller's key may hold, after evicting the key's idle sessions
    /// if that makes it fit ([`Self::make_room`]). Blocking.
    fn check_group_bytes(
        &self,
        total: &SessionCost,
        owner: &session::Owner,
        n: usize,
    ) -> Result<(), ServiceError> {
        self.make_room(owner, total.bytes);
        let held = self.sessions.read().usage(owner);
        let sum = held.bytes.saturating_add(total.bytes);
        if sum > self.limits.max_key_bytes {
            return Err(ServiceError::QuotaExceeded(format!(
                "this API key's sessions would hold an estimated {sum} bytes ({} now, {} for the \
                 group's {n} members); its quota is {} (--max-key-bytes)",
                held.bytes, total.bytes, self.limits.max_key_bytes
            )));
        }
        Ok(())
    }

    /// The group with this id if `caller` may see it; another key's group
    /// is `GroupNotFound`, exactly like a missing one. Clustered, a group
    /// whose shard is not served here is refused as a session would be.
    pub fn group_for(&self, caller: Caller, id: &str) -> Result<Arc<Group>, ServiceError> {
        if let Some(p) = &self.placement {
            p.check(id).map_err(|e| match ServiceError::from(e) {
                ServiceError::NotFound(id) => ServiceError::GroupNotFound(id),
                e => e,
            })?;
        }
        let group = self
            .groups
            .read()
            .get(id)
            .cloned()
            .ok_or_else(|| ServiceError::GroupNotFound(id.to_string()))?;
        if !caller.may_see(group.owner.as_ref()) {
            return Err(ServiceError::GroupNotFound(id.to_string()));
        }
        Ok(group)
    }

    /// A group: its seed, shape and members.
    pub fn get_group(&self, caller: Caller, id: &str) -> Result<GroupInfo, ServiceError> {
        Ok(self.group_for(caller, id)?.info())
    }

    /// Deletes every member of a group (each as [`Self::delete`] deletes a
    /// session, its stored data included), then the group. A member
    /// already deleted on its own is skipped; if a member's deletion fails,
    /// the group stays with the members not yet deleted, and the error is
    /// returned (retry).
    pub async fn delete_group(&self, caller: Caller, id: &str) -> Result<(), ServiceError> {
        let group = self.group_for(caller, id)?;
        let deletions = group
            .members
            .iter()
            .flatten()
            .map(|member| self.delete(caller, member));
        for result in join_all(deletions).await {
            match result {
                Ok(()) | Err(ServiceError::NotFound(_)) => {}
                Err(e) => return Err(e),
            }
        }
        self.groups.write().remove(id);
        tracing::info!(group = %id, "group deleted");
        Ok(())
    }

    /// One step of a group by columns (docs/groups.md, "Stepping"): the
    /// columns are checked against the group first and the step refused
    /// whole if they do not fit; then every member stepped observes its
    /// observation as [`Self::observe`] would apply it alone and answers
    /// its step or its own refusal, in mask order. A refused member does
    /// not stop the others. With `seqs`, each member's observation carries
    /// its seq: a member that already applied it answers its recorded step
    /// (`replayed`) and applies nothing, one whose session refuses it
    /// (`seq_gap`, `seq_expired`, `seq_conflict`) is refused alone, as the
    /// same observation sent alone would be.
    ///
    /// Members whose update is cheap (the hallway's takes about a
    /// microsecond) are applied in one chunk per tick worker (at least
    /// [`STEP_CHUNK`] members each) on the blocking pool, with one session
    /// lookup each and no task of their own, and their commits are awaited
    /// together after the last is applied: the cost of a member is then its
    /// update and little else. The others (an
    /// evicted member loaded back, an update beyond the inline budget, a
    /// step while the store refuses writes) take [`Self::observe`]'s path,
    /// concurrently.
    pub async fn step_group(
        self: &Arc<Self>,
        caller: Caller,
        id: &str,
        columns: Columns,
    ) -> Result<Vec<MemberStep>, ServiceError> {
        let group = self.group_for(caller, id)?;
        let stepped = group.observations(columns)?;
        // The members share their model and configuration, so one's
        // estimate prices them all (as `check_message_cost` would, without
        // a lookup per member).
        let us = group.tick_us.saturating_mul(stepped.len() as u64);
        if us / 1000 > self.limits.max_batch_ms {
            return Err(ServiceError::LimitExceeded(format!(
                "the step's {} members cost an estimated {} ms in all; the limit per message \
                 is {} ms (--max-batch-ms): step fewer members per message",
                stepped.len(),
                us / 1000,
                self.limits.max_batch_ms
            )));
        }
        self.panic_if_asked();
        let m = stepped.len();
        let indices: Vec<usize> = stepped.iter().map(|(index, _)| *index).collect();
        let mut results: Vec<Option<Result<StepOut, ServiceError>>> =
            std::iter::repeat_with(|| None).take(m).collect();
        let mut slow: Vec<(usize, usize, ObservationIn)> = Vec::new();
        if self.store_writable().is_ok() {
            // Held until every commit is awaited, as `observe` holds it: a
            // shard is not frozen under a step half applied.
            let _guard = self.enter_shard(id)?;
            // The chunks read their members' observations where they are,
            // in the one vector they share, instead of each moving its own
            // out of it (an observation is about 150 bytes).
            let size = STEP_CHUNK.max(m.div_ceil(self.workers));
            let stepped = Arc::new(stepped);
            let chunks: Vec<_> = (0..m)
                .step_by(size)
                .map(|start| {
                    let range = start..(start + size).min(m);
                    let (manager, group) = (Arc::clone(self), Arc::clone(&group));
                    let stepped = Arc::clone(&stepped);
                    tokio::task::spawn_blocking(move || {
                        manager.apply_members(caller, &group, &stepped[range.clone()], range.start)
                    })
                })
                .collect();
            // Each chunk's outcomes stay where the chunk left them, in member
            // order, and are read once the commits are in: a member's reply
            // (about 150 bytes with its session and commit) is moved once,
            // into `results`.
            let mut parts = Vec::with_capacity(chunks.len());
            let mut sent = Vec::with_capacity(chunks.len());
            for chunk in join_all(chunks).await {
                let (part, batch) = chunk.map_err(|e| {
                    ServiceError::Internal(format!("a group step task failed: {e}"))
                })?;
                sent.push(batch);
                parts.push(part);
            }
            // The chunks' batches were sent one after the other and share
            // group commits: the first wait is the only one that waits.
            let mut outcomes = Vec::with_capacity(sent.len());
            for batch in sent {
                outcomes.push(batch.wait().await);
            }
            let mut applied = 0u64;
            let mut elsewhere = Vec::new();
            for (part, outcome) in parts.into_iter().zip(&outcomes) {
                for (pos, applying) in part {
                    let result = match applying {
                        Applied::Done(session, observed) => {
                            applied += 1;
                            let result = if observed.waits() {
                                observed.durable_in(outcome).await
                            } else {
                                observed.settled_in(outcome)
                            };
                            let result = result.and_then(|out| {
                                super::observe::replays_stand(&session, &out)?;
                                only_step(out)
                            });
                            self.roll_back_if_uncommitted(&session, &result);
                            result
                        }
                        Applied::Refused(e) => Err(e),
                        Applied::Elsewhere => {
                            elsewhere.push(pos);
                            continue;
                        }
                    };
                    results[pos] = Some(result);
                }
            }
            tick::meters().observations.increment(applied);
            if !elsewhere.is_empty() {
                // Every chunk's task has ended and dropped its share.
                let mut stepped = Arc::try_unwrap(stepped).map_err(|_| {
                    ServiceError::Internal("a group step's chunks outlived it".into())
                })?;
                slow = elsewhere
                    .into_iter()
                    .map(|pos| {
                        let (index, obs) = std::mem::take(&mut stepped[pos]);
                        (pos, index, obs)
                    })
                    .collect();
            }
        } else {
            slow = stepped
                .into_iter()
                .enumerate()
                .map(|(pos, (index, obs))| (pos, index, obs))
                .collect();
        }
        let slow = slow.into_iter().map(|(pos, index, obs)| {
            let member = group.members[index].clone();
            let group = &group;
            async move {
                let result = match member {
                    Some(member) => self
                        .observe(caller, &member, vec![obs])
                        .await
                        .and_then(only_step),
                    None => Err(unrecovered(&group.id, index)),
                };
                (pos, result)
            }
        });
        for (pos, result) in join_all(slow).await {
            results[pos] = Some(result);
        }
        Ok(group_steps(&group, indices, results))
    }

    /// Applies a chunk of a group step's members on this (blocking) thread:
    /// each resident member whose update is cheap, as [`Self::observe`]
    /// would, its log entry into the chunk's batch (sent at the end); the
    /// rest are left to its path.
    fn apply_members(
        &self,
        caller: Caller,
        group: &Group,
        chunk: &[(usize, ObservationIn)],
        first: usize,
    ) -> (Vec<(usize, Applied)>, Sent) {
        let batch = self
            .durability
            .as_ref()
            .map(|d| Arc::new(Batch::expecting(Arc::clone(&d.store), chunk.len())));
        let mut resident: Vec<Option<SessionRef>> = {
            let table = self.sessions.read();
            let mut slots = group.resolved.lock();
            chunk
                .iter()
                .map(|(index, _)| Resolved::resident(&mut slots, &table, &group.members, *index))
                .collect()
        };
        let applied = chunk
            .iter()
            .enumerate()
            .map(|(k, &(index, ref obs))| {
                let pos = first + k;
                // Ten thousand members' tables are in no cache when their
                // turn comes: the CPU loads the next member's while this
                // one is stepped, and the one after's session struct.
                if let Some(Some(next)) = resident.get(k + 2) {
                    mcapi_core::prefetch::value::<Session>(next);
                }
                if let Some(Some(next)) = resident.get(k + 1) {
                    next.prefetch();
                }
                let resident = resident[k].take();
                if group.members[index].is_none() {
                    return (pos, Applied::Refused(unrecovered(&group.id, index)));
                }
                let session = match resident {
                    Some(s) if caller.may_see(s.owner.as_ref()) && !s.is_stale() => s,
                    // Evicted, deleted, or to be rolled back first: as a
                    // lone observation is.
                    _ => return (pos, Applied::Elsewhere),
                };
                if session.is_failed() {
                    let e = ServiceError::SessionFailed(session.id.clone());
                    return (pos, Applied::Refused(e));
                }
                let observed =
                    self.observe_inline(&session, std::slice::from_ref(obs), batch.as_ref());
                let outcome = match observed {
                    Some(observed) => Applied::Done(session, observed),
                    None => Applied::Elsewhere,
                };
                (pos, outcome)
            })
            .collect();
        (applied, batch.map(|b| b.finish()).unwrap_or_default())
    }

    /// Registers the groups of these sessions (recovered at start, or
    /// imported with their shard): each session's record names its group,
    /// size and index.
    pub(super) fn register_groups(&self, members: impl IntoIterator<Item = GroupMember>) {
        let mut found: BTreeMap<String, Group> = BTreeMap::new();
        for GroupMember {
            tag,
            id,
            model,
            mode,
            owner,
            tick_us,
        } in members
        {
            let size = tag.size as usize;
            let index = tag.index as usize;
            if index >= size {
                tracing::warn!(session = %id, group = %tag.group, "a group member's index is beyond its group; ignored");
                continue;
            }
            let group = found.entry(tag.group.clone()).or_insert_with(|| Group {
                id: tag.group.clone(),
                owner,
                seed: tag.seed,
                members: vec![None; size],
                model,
                mode,
                tick_us,
                resolved: Resolved::default(),
            });
            if let Some(slot) = group.members.get_mut(index) {
                *slot = Some(id);
            }
        }
        let mut groups = self.groups.write();
        for (id, group) in found {
            groups.insert(id, Arc::new(group));
        }
    }

    /// Forgets the groups whose id begins with `prefix` (their shard moved
    /// away with their members).
    pub(super) fn remove_groups(&self, prefix: &str) {
        self.groups.write().retain(|id, _| !id.starts_with(prefix));
    }

    /// Number of groups in memory.
    pub fn groups_len(&self) -> usize {
        self.groups.read().len()
    }
}

/// The fewest members of a group step applied per task of the blocking
/// pool: enough that the hand-off (some microseconds) is small beside
/// their updates (about a microsecond each for the hallway). A larger step
/// is cut into one part per tick worker (`--workers`, by default one per
/// CPU the process may run on), so it is spread over every core and no
/// more tasks than cores take turns on one: ten parts of 512 members on a
/// server given one core switched threads and evicted each other's cached
/// agents for nothing.
const STEP_CHUNK: usize = 512;

/// What became of one member in [`SessionManager::apply_members`].
enum Applied {
    /// Applied here; its commit is still to be awaited.
    Done(SessionRef, session::Observed),
    /// Refused before anything was applied.
    Refused(ServiceError),
    /// Not applied here: it takes [`SessionManager::observe`]'s path.
    Elsewhere,
}

/// The one step of a member's one observation.
fn only_step(mut steps: Vec<StepOut>) -> Result<StepOut, ServiceError> {
    steps
        .pop()
        .ok_or_else(|| ServiceError::Internal("observe returned no step".into()))
}

/// A member whose records could not be recovered from the store.
fn unrecovered(group: &str, index: usize) -> ServiceError {
    ServiceError::NotFound(format!(
        "{group}[{index}] (this member could not be recovered from the store)"
    ))
}

/// The replies of a group step in mask order, from the members' results.
fn group_steps(
    group: &Group,
    indices: Vec<usize>,
    results: Vec<Option<Result<StepOut, ServiceError>>>,
) -> Vec<MemberStep> {
    indices
        .into_iter()
        .zip(results)
        .map(|(index, result)| MemberStep {
            index,
            result: result.unwrap_or_else(|| {
                Err(ServiceError::Internal(format!(
                    "{}: a member of the step was neither applied nor refused",
                    group.id
                )))
            }),
        })
        .collect()
}
