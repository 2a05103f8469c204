//! A batch of transitions as tensors: the interface between the replay buffers and the SAC update.
use crate::error::{LearnerError, Result};
use tch::{Device, Kind, Tensor};

/// Transitions `(s, a, r, mask, s')`, one row each.
#[derive(Debug)]
pub struct Batch {
    /// `[N, D]`
    pub obs: Tensor,
    /// `[N, A]`
    pub action: Tensor,
    /// `[N]`
    pub reward: Tensor,
    /// `[N]`: 0 on a true termination, else 1 (spec 5.6).
    pub mask: Tensor,
    /// `[N, D]`
    pub next_obs: Tensor,
}

/// The same fields as flat row-major f32 slices (what the replay gathers into).
#[derive(Debug, Default, Clone, PartialEq)]
pub struct HostBatch {
    pub obs_dim: usize,
    pub action_dim: usize,
    pub obs: Vec<f32>,
    pub action: Vec<f32>,
    pub reward: Vec<f32>,
    pub mask: Vec<f32>,
    pub next_obs: Vec<f32>,
}

impl HostBatch {
    /// An empty batch with room for `rows` rows.
    pub fn with_capacity(rows: usize, obs_dim: usize, action_dim: usize) -> Self {
        Self {
            obs_dim,
            action_dim,
            obs: Vec::with_capacity(rows * obs_dim),
            action: Vec::with_capacity(rows * action_dim),
            reward: Vec::with_capacity(rows),
            mask: Vec::with_capacity(rows),
            next_obs: Vec::with_capacity(rows * obs_dim),
        }
    }

    pub fn rows(&self) -> usize {
        self.reward.len()
    }

    /// Copies the rows into tensors of `kind` on `device`.
    pub fn to_tensors(&self, kind: Kind, device: Device) -> Batch {
        let rows = self.rows() as i64;
        let put = |v: &[f32], cols: Option<usize>| {
            let t = Tensor::from_slice(v);
            let t = match cols {
                Some(c) => t.view([rows, c as i64]),
                None => t,
            };
            t.to_kind(kind).to_device(device)
        };
        Batch {
            obs: put(&self.obs, Some(self.obs_dim)),
            action: put(&self.action, Some(self.action_dim)),
            reward: put(&self.reward, None),
            mask: put(&self.mask, None),
            next_obs: put(&self.next_obs, Some(self.obs_dim)),
        }
    }
}

impl Batch {
    pub fn rows(&self) -> i64 {
        self.reward.size()[0]
    }

    /// Rows `[index·size, (index+1)·size)` as views (no copy): minibatch `index` of spec 5.2.
    pub fn minibatch(&self, index: i64, size: i64) -> Result<Batch> {
        let start = index * size;
        if start + size > self.rows() {
            return Err(LearnerError::Shape(format!(
                "minibatch {index} of {size} rows needs {} rows, the batch has {}",
                start + size,
                self.rows()
            )));
        }
        Ok(Batch {
            obs: self.obs.narrow(0, start, size),
            action: self.action.narrow(0, start, size),
            reward: self.reward.narrow(0, start, size),
            mask: self.mask.narrow(0, start, size),
            next_obs: self.next_obs.narrow(0, start, size),
        })
    }
}
