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

/// What a slice of the state vector measures ([`StateLayout::parts`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Quantity {
    /// Positions in metres, joint positions, and the other configuration values a state holds
    /// (MetaWorld's goal vector, PointMaze's collision flag).
    Position,
    /// A unit quaternion (w, x, y, z).
    Orientation,
    /// Linear, angular or joint velocities.
    Velocity,
    /// An opaque MS2 flat state, whose entries' kinds are unknown.
    Value,
}

/// One slice of the state vector and what it measures, e.g. `actors/cube position`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StatePart {
    pub name: String,
    pub quantity: Quantity,
    pub range: Range<usize>,
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

    /// The state vector split by what each slice measures, in layout order: an MS3 actor is a
    /// position, an orientation and two velocities; an articulation its root's three and then
    /// its joints' positions and velocities; a named field is a velocity when its name says so
    /// (`qvel`, `*vel`), an orientation when it is a 4-value `*quat`, else a position; a flat MS2
    /// state is one opaque value. The demo check judges each kind with its own tolerance
    /// (docs/SUITES.md "Checking demos").
    pub fn parts(&self) -> Vec<StatePart> {
        let mut parts = Vec::new();
        for e in &self.entries {
            let mut push = |what: &str, quantity: Quantity, start: usize, len: usize| {
                let name = if what.is_empty() {
                    e.name.clone()
                } else {
                    format!("{} {what}", e.name)
                };
                let start = e.offset + start;
                parts.push(StatePart {
                    name,
                    quantity,
                    range: start..start + len,
                });
            };
            match e.kind {
                StateKind::Flat => push("", Quantity::Value, 0, e.len),
                StateKind::Actor | StateKind::Articulation => {
                    let root = if e.kind == StateKind::Actor {
                        ""
                    } else {
                        "root "
                    };
                    push(&format!("{root}position"), Quantity::Position, 0, 3);
                    push(&format!("{root}orientation"), Quantity::Orientation, 3, 4);
                    push(&format!("{root}linear velocity"), Quantity::Velocity, 7, 3);
                    push(
                        &format!("{root}angular velocity"),
                        Quantity::Velocity,
                        10,
                        3,
                    );
                    if let Some(dof) = e.dof().filter(|&d| d > 0) {
                        push("qpos", Quantity::Position, StateKind::ROOT_LEN, dof);
                        push("qvel", Quantity::Velocity, StateKind::ROOT_LEN + dof, dof);
                    }
                }
                StateKind::Field => {
                    let quantity = if e.name.ends_with("vel") {
                        Quantity::Velocity
                    } else if e.name.ends_with("quat") && e.len == 4 {
                        Quantity::Orientation
                    } else {
                        Quantity::Position
                    };
                    push("", quantity, 0, e.len);
                }
            }
        }
        parts
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

#[cfg(test)]
mod tests {
    use super::*;

    fn summary(layout: &StateLayout) -> Vec<(String, Quantity, Range<usize>)> {
        layout
            .parts()
            .into_iter()
            .map(|p| (p.name, p.quantity, p.range))
            .collect()
    }

    #[test]
    fn parts_split_each_kind_by_what_it_measures() {
        use Quantity::*;
        let ms3 = StateLayout::from_parts([
            ("actors/cube".to_owned(), StateKind::Actor, 13),
            (
                "articulations/arm".to_owned(),
                StateKind::Articulation,
                13 + 2 * 2,
            ),
        ]);
        let expected = [
            ("actors/cube position", Position, 0..3),
            ("actors/cube orientation", Orientation, 3..7),
            ("actors/cube linear velocity", Velocity, 7..10),
            ("actors/cube angular velocity", Velocity, 10..13),
            ("articulations/arm root position", Position, 13..16),
            ("articulations/arm root orientation", Orientation, 16..20),
            ("articulations/arm root linear velocity", Velocity, 20..23),
            ("articulations/arm root angular velocity", Velocity, 23..26),
            ("articulations/arm qpos", Position, 26..28),
            ("articulations/arm qvel", Velocity, 28..30),
        ]
        .map(|(n, q, r)| (n.to_owned(), q, r));
        assert_eq!(summary(&ms3), expected);
        let fields = StateLayout::from_parts(
            [
                ("qpos", 9),
                ("qvel", 9),
                ("mocap_quat", 4),
                ("desired_quat", 3),
                ("collided", 1),
            ]
            .map(|(n, len)| (n.to_owned(), StateKind::Field, len)),
        );
        let quantities: Vec<Quantity> = fields.parts().iter().map(|p| p.quantity).collect();
        assert_eq!(
            quantities,
            [Position, Velocity, Orientation, Position, Position]
        );
        assert_eq!(
            summary(&StateLayout::flat(5)),
            [("env_states".to_owned(), Value, 0..5)]
        );
    }
}
