//! A snapshot encoded as the server's durable store writes it, and as it
//! wrote it before it borrowed its agents: the benches of both compare the
//! two. (This crate may not depend on the server's, so the few lines of
//! `service::durable::encode` stand here once for every bench.)

/// `value` as the store writes it: a record-version byte, then postcard,
/// into a buffer sized by a counting pass first.
pub fn sized(value: &impl serde::Serialize) -> Vec<u8> {
    let len = postcard::serialize_with_flavor(value, postcard::ser_flavors::Size::default())
        .expect("size");
    let mut out = Vec::with_capacity(1 + len);
    out.push(RECORD_VERSION);
    postcard::to_extend(value, out).expect("encode")
}

/// `value` as it was written before: the version byte, then postcard into
/// a buffer that grows as it goes.
pub fn growing(value: &impl serde::Serialize) -> Vec<u8> {
    postcard::to_extend(value, vec![RECORD_VERSION]).expect("encode")
}

/// The record-version byte in front of a stored snapshot.
const RECORD_VERSION: u8 = 5;
