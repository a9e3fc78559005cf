//! The hallway as a client simulates it: a 50-state chain its agent moves
//! along (left, right, stay), stimulus `[6, 0]` at state 10 and `[0, 6]`
//! at 40, and its next observation as REST JSON or as protobuf.

use mcapi_proto as pb;

/// The hallway as a client simulates it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hallway {
    state: usize,
    started: bool,
    /// The `seq` of the next observation, when observations carry one
    /// (`--seq`: exactly-once delivery, docs/sessions.md).
    seq: Option<u64>,
}

impl Hallway {
    const STATES: usize = 50;
    const START: usize = 25;
    const FOOD: usize = 10;
    const REST: usize = 40;

    pub(crate) fn new() -> Self {
        Self {
            state: Self::START,
            started: false,
            seq: None,
        }
    }

    /// This world with its observations numbered from seq 0 (REST only).
    pub(crate) fn numbered(self, numbered: bool) -> Self {
        Self {
            seq: numbered.then_some(0),
            ..self
        }
    }

    /// The stimulus received on arrival in the current state.
    fn stimulus(&self) -> [f64; 2] {
        match self.state {
            Self::FOOD => [6.0, 0.0],
            Self::REST => [0.0, 6.0],
            _ => [0.0, 0.0],
        }
    }

    /// The next observation as JSON (no stimulus on the first).
    pub(crate) fn json(&self) -> String {
        let seq = self
            .seq
            .map(|n| format!(r#","seq":{n}"#))
            .unwrap_or_default();
        if self.started {
            let [a, b] = self.stimulus();
            format!(
                r#"{{"state":{},"stimulus":[{a:?},{b:?}]{seq}}}"#,
                self.state
            )
        } else {
            format!(r#"{{"state":{}{seq}}}"#, self.state)
        }
    }

    /// The next observation as protobuf (no stimulus on the first).
    pub(crate) fn proto(&self) -> pb::Observation {
        pb::Observation {
            // Named by the stream's `x-mcapi-session` metadata instead.
            session_id: String::new(),
            state: self.state as u64,
            stimulus: self.started.then(|| pb::Stimulus {
                values: self.stimulus().to_vec(),
            }),
            action_taken: None,
            ..Default::default()
        }
    }

    /// Moves by the advised action: 0 left, 1 right, 2 stay.
    pub(crate) fn advance(&mut self, action: usize) {
        self.state = match action {
            0 => self.state.saturating_sub(1),
            1 => (self.state + 1).min(Self::STATES - 1),
            _ => self.state,
        };
        self.started = true;
        self.seq = self.seq.map(|n| n + 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hallway_moves_and_stimuli() {
        let mut w = Hallway::new();
        assert_eq!(w.json(), r#"{"state":25}"#);
        let mut n = Hallway::new().numbered(true);
        assert_eq!(n.json(), r#"{"state":25,"seq":0}"#);
        n.advance(2);
        assert_eq!(n.json(), r#"{"state":25,"stimulus":[0.0,0.0],"seq":1}"#);
        for _ in 0..15 {
            w.advance(0);
        }
        assert_eq!(w.state, 10);
        assert_eq!(w.json(), r#"{"state":10,"stimulus":[6.0,0.0]}"#);
        w.advance(2);
        assert_eq!(w.state, 10);
        for _ in 0..100 {
            w.advance(1);
        }
        assert_eq!(w.state, 49);
        assert_eq!(w.proto().stimulus.map(|s| s.values), Some(vec![0.0, 0.0]));
    }
}
