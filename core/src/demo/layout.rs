use std::ops::Range;

use serde::{Deserialize, Serialize};

/// What an entry of the flat env-state vector holds (spec 6.1, 7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StateKind {
    /// An MS2 flat state: the whole vector, opaque (spec 7.2).
    Flat,
    /// An MS3 actor: pos 3, quat 4, linear velocity 3, angular velocity 3 (spec 7.1).
    Actor,
    /// An MS3 articulation: root pose 7, root velocity 6, qpos dof, qvel dof (spec 7.1).
    Articulation,
    /// A named field (Adroit, MetaWorld: spec 7.3, 7.4).
    Field,
}

impl StateKind {
    /// The one length an MS3 actor's state has.
    pub const ACTOR_LEN: usize = 13;
    /// The part of an MS3 articulation's state before qpos and qvel.
    pub const ROOT_LEN: usize = 13;
}

/// One named slice of the flat env-state vector.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateEntry {
    /// Path below `env_states` in the file: `actors/cube`, `articulations/panda`, `qpos`;
    /// `env_states` for the flat form.
    pub name: String,
    pub kind: StateKind,
    pub offset: usize,
    pub len: usize,
}

impl StateEntry {
    pub fn range(&self) -> Range<usize> {
        self.offset..self.offset + self.len
    }

    /// An articulation's degrees of freedom, (len − 13) / 2.
    pub fn dof(&self) -> Option<usize> {
        (self.kind == StateKind::Articulation)
            .then(|| self.len.saturating_sub(StateKind::ROOT_LEN) / 2)
    }
}

/// How a flat env-state vector splits into named parts, so that a simulator adapter can rebuild
/// its state dict by name. Entries are contiguous and in order, starting at offset 0.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(try_from = "Vec<StateEntry>", into = "Vec<StateEntry>")]
pub struct StateLayout {
    entries: Vec<StateEntry>,
}

impl StateLayout {
    /// The MS2 form: one opaque entry named `env_states`.
    pub fn flat(dim: usize) -> Self {
        Self::from_parts([("env_states".to_owned(), StateKind::Flat, dim)])
    }

    /// Lays out `(name, kind, len)` parts back to back, in the given order.
    pub fn from_parts(parts: impl IntoIterator<Item = (String, StateKind, usize)>) -> Self {
        let mut offset = 0;
        let entries = parts
            .into_iter()
            .map(|(name, kind, len)| {
                let entry = StateEntry {
                    name,
                    kind,
                    offset,
                    len,
                };
                offset += len;
                entry
            })
            .collect();
        Self { entries }
    }

    pub fn entries(&self) -> &[StateEntry] {
        &self.entries
    }

    /// The length of the flat vector.
    pub fn dim(&self) -> usize {
        self.entries.last().map_or(0, |e| e.offset + e.len)
    }

    /// True for the MS2 form, written back as one flat dataset.
    pub fn is_flat(&self) -> bool {
        matches!(self.entries.as_slice(), [e] if e.kind == StateKind::Flat)
    }

    pub fn get(&self, name: &str) -> Option<&StateEntry> {
        self.entries.iter().find(|e| e.name == name)
    }

    /// The part of `state` that belongs to `name`.
    pub fn slice<'a>(&self, name: &str, state: &'a [f32]) -> Option<&'a [f32]> {
        self.get(name).and_then(|e| state.get(e.range()))
    }

    /// A one-line description, e.g. `actors/cube (13), articulations/panda (31)`.
    pub fn describe(&self) -> String {
        let parts: Vec<String> = self
            .entries
            .iter()
            .map(|e| format!("{} ({})", e.name, e.len))
            .collect();
        parts.join(", ")
    }
}

impl TryFrom<Vec<StateEntry>> for StateLayout {
    type Error = String;

    /// Accepts entries only when they are contiguous from offset 0.
    fn try_from(entries: Vec<StateEntry>) -> Result<Self, String> {
        let mut offset = 0;
        for e in &entries {
            if e.offset != offset {
                return Err(format!(
                    "state entry {} starts at {} but should at {offset}",
                    e.name, e.offset
                ));
            }
            offset += e.len;
        }
        Ok(Self { entries })
    }
}

impl From<StateLayout> for Vec<StateEntry> {
    fn from(layout: StateLayout) -> Self {
        layout.entries
    }
}
