//! The one session layer both transports call (docs/architecture.md, "The layers"): create,
//! get, list, delete, observe, values and history of hosted agents, the
//! limits, and the tick loop that runs policy updates off the request path.
//!
//! Read from the outside in:
//! - [`wire`]: what calls take and answer (JSON and OpenAPI derives);
//!   [`agent_config`]: the agent configuration, defined once; [`spec`]: a
//!   model in its three posted forms.
//! - [`manager`]: [`SessionManager`], the entry point, routing each call;
//!   [`setup`] builds a session, [`values`] reads its value tables.
//! - [`session`]: one hosted agent ([`learner`], its [`history`] ring, its
//!   log), [`table`] of sessions, [`tick`] pool.
//! - [`durable`]: what is kept in the store; [`recovery`]: rebuilding
//!   sessions from it, at start and after a failed commit.
//! - [`limits`], [`cost`], [`auth`], [`error`].

pub mod agent_config;
pub mod auth;
pub mod budget;
pub mod cost;
pub mod durable;
pub mod error;
pub mod groups;
pub mod history;
pub mod learner;
pub mod limits;
pub mod manager;
pub mod membership;
pub mod recovery;
pub mod session;
pub mod setup;
pub mod shards;
pub mod spec;
pub mod table;
pub mod tick;
pub mod values;
pub mod wire;

#[cfg(test)]
mod fault_tests;
#[cfg(test)]
mod test_support;

pub use agent_config::{CuriosityConfig, EffectiveConfig, SessionConfig, UpdateMode};
pub use auth::{ApiKeys, Caller};
pub use error::{DecodeError, RecordError, RecoveryError, ServiceError, StorageError};
pub use learner::Learner;
pub use limits::{Limits, Usage};
pub use manager::{
    AbandonOnDrop, DEFAULT_INLINE_PLAN, DEFAULT_PAGE, DEFAULT_SNAPSHOT_EVERY, MAX_PAGE,
    ManagerOptions, SHARDS, SessionManager, Watch,
};
pub use recovery::RecoveryReport;
pub use session::{Durability, Session, SessionRef};
pub use spec::ModelInput;
pub use values::ValueSelection;
pub use wire::{
    BasisSummary, CreateSession, CuriosityInfo, FrozenModuleInfo, HistoryEntry, ModelSummary,
    ObservationIn, SessionCost, SessionInfo, SessionPage, SessionStats, SessionSummary, StepOut,
    TickCuriosity, Values,
};
