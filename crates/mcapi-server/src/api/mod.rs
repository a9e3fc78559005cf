//! Thin transport adapters over [`crate::service`]: REST (axum) and gRPC
//! (tonic), with one error mapping.

pub mod conn;
pub mod dashboard;
pub mod error;
pub mod grpc;
pub mod openapi;
pub mod rest;
pub mod streams;
