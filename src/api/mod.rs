//! Thin transport adapters over [`crate::service`]: REST (axum) and gRPC
//! (tonic), with one error mapping.

pub mod error;
pub mod grpc;
pub mod rest;
