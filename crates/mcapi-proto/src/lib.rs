//! The gRPC API of mcapi, package `mcapi.v1` (docs/grpc.md): the prost
//! messages and the tonic client and server generated from
//! `proto/mcapi/v1/agents.proto` at the workspace's top level, shared by the
//! server (`mcapi-server`) and the load generator (`mcapi-loadgen`).

#![allow(missing_docs)]

tonic::include_proto!("mcapi.v1");

/// The encoded descriptor set of the protos, for reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/mcapi_descriptor.bin"));

/// Metadata key naming the session a call concerns (docs/sessions.md, "Session ids and ownership"):
/// routers cannot read message bodies, so clients send the id here too.
pub const SESSION_METADATA: &str = "x-mcapi-session";

impl Model {
    /// A preset model by name (`hallway` or `three_room`), with its own basis.
    pub fn preset(name: impl Into<String>) -> Self {
        Self {
            form: Some(model::Form::Preset(PresetModel {
                name: name.into(),
                basis: None,
            })),
        }
    }
}
