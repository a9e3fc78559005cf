//! API keys (docs/operations.md, "API keys"): with keys configured, every
//! call names one in `Authorization: Bearer <key>` and sees only the
//! sessions created with it.
//!
//! Keys are kept and compared as SHA-256 digests: a presented key is hashed
//! once and compared with every configured digest in constant time, so
//! neither the position of the first differing byte nor which key matched
//! shows in the timing. Digests, not keys, are stored as session owners, and
//! neither keys nor digests are logged.

use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use super::error::ServiceError;

/// Who is calling.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Caller {
    /// No keys are configured: everyone sees every session.
    Anyone,
    /// The holder of the key with this digest.
    Key([u8; 32]),
}

impl std::fmt::Debug for Caller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Anyone => f.write_str("Anyone"),
            // Never print the digest: it identifies the key.
            Self::Key(_) => f.write_str("Key(..)"),
        }
    }
}

impl Caller {
    /// The owner recorded on sessions this caller creates.
    pub fn owner(self) -> Option<[u8; 32]> {
        match self {
            Self::Anyone => None,
            Self::Key(d) => Some(d),
        }
    }

    /// Whether this caller may see a session with this owner.
    pub fn may_see(self, owner: Option<&[u8; 32]>) -> bool {
        match self {
            Self::Anyone => true,
            Self::Key(d) => owner.is_some_and(|o| bool::from(o.ct_eq(&d))),
        }
    }
}

/// The configured keys, as digests.
#[derive(Clone, Default)]
pub struct ApiKeys {
    digests: Vec<[u8; 32]>,
}

impl std::fmt::Debug for ApiKeys {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ApiKeys({} keys)", self.digests.len())
    }
}

fn digest(key: &str) -> [u8; 32] {
    Sha256::digest(key.as_bytes()).into()
}

impl ApiKeys {
    /// Keys from their plain text; empty strings are ignored.
    pub fn new<S: AsRef<str>>(keys: impl IntoIterator<Item = S>) -> Self {
        let mut digests: Vec<[u8; 32]> = keys
            .into_iter()
            .map(|k| k.as_ref().trim().to_string())
            .filter(|k| !k.is_empty())
            .map(|k| digest(&k))
            .collect();
        digests.sort_unstable();
        digests.dedup();
        Self { digests }
    }

    /// True when keys are required.
    pub fn enabled(&self) -> bool {
        !self.digests.is_empty()
    }

    /// The caller of a request with this `Authorization` header value.
    pub fn authenticate(&self, authorization: Option<&str>) -> Result<Caller, ServiceError> {
        if !self.enabled() {
            return Ok(Caller::Anyone);
        }
        let header = authorization.ok_or_else(|| {
            ServiceError::Unauthenticated(
                "an API key is required: send `Authorization: Bearer <key>`".into(),
            )
        })?;
        let key = header
            .strip_prefix("Bearer ")
            .or_else(|| header.strip_prefix("bearer "))
            .map(str::trim)
            .filter(|k| !k.is_empty())
            .ok_or_else(|| {
                ServiceError::Unauthenticated(
                    "the `Authorization` header must be `Bearer <key>`".into(),
                )
            })?;
        let presented = digest(key);
        // Every configured digest is compared, whatever matched before.
        let mut found = subtle::Choice::from(0);
        for d in &self.digests {
            found |= d.ct_eq(&presented);
        }
        if bool::from(found) {
            Ok(Caller::Key(presented))
        } else {
            Err(ServiceError::Unauthenticated(
                "the API key is not valid".into(),
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_checked_and_callers_see_only_their_own() {
        let keys = ApiKeys::new(["alpha", "beta", " "]);
        assert!(keys.enabled());
        let a = keys.authenticate(Some("Bearer alpha")).expect("alpha");
        let b = keys.authenticate(Some("Bearer beta")).expect("beta");
        assert_ne!(a, b);
        for bad in [
            None,
            Some("alpha"),
            Some("Bearer "),
            Some("Bearer gamma"),
            Some("Basic alpha"),
        ] {
            let err = keys.authenticate(bad).expect_err("refused");
            assert!(matches!(err, ServiceError::Unauthenticated(_)), "{bad:?}");
            assert!(
                !err.to_string().contains("alpha"),
                "the key must not be echoed"
            );
        }
        assert!(a.may_see(a.owner().as_ref()));
        assert!(!a.may_see(b.owner().as_ref()));
        assert!(!a.may_see(None));
        assert!(Caller::Anyone.may_see(a.owner().as_ref()));
        assert!(format!("{a:?}").eq("Key(..)"));
    }

    #[test]
    fn without_keys_everyone_is_let_in() {
        let keys = ApiKeys::new(Vec::<String>::new());
        assert!(!keys.enabled());
        assert_eq!(keys.authenticate(None).expect("open"), Caller::Anyone);
        assert_eq!(
            keys.authenticate(Some("Bearer whatever")).expect("open"),
            Caller::Anyone
        );
    }
}
