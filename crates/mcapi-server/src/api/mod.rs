//! Thin transport adapters over [`crate::service`]: REST (axum) and gRPC
//! (tonic), with one error mapping.

pub mod admin;
pub mod coalesce;
pub mod conn;
pub mod dashboard;
pub mod error;
pub mod extract;
pub mod grpc;
pub mod observe_body;
pub mod openapi;
pub mod rest;
pub mod router;
pub mod schemas;
pub mod streams;

pub use extract::{AppState, Serving};
pub use router::router;
