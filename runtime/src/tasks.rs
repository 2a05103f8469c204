//! A service's named tasks under one supervisor (the curriculum server's gRPC server, dashboard
//! and duties; the learner's; the actor's): every task must run until the stop, so one that ends
//! early is an error naming it, and a stop waits for all of them at most a grace period, then
//! aborts and names the rest.
use std::collections::HashMap;
use std::future::Future;
use std::time::Duration;

use tokio::task::JoinSet;
use tokio::time::Instant;

/// A service's tasks, by name: each must run until the stop.
#[derive(Default)]
pub struct Tasks {
    set: JoinSet<anyhow::Result<()>>,
    names: HashMap<tokio::task::Id, &'static str>,
}

impl Tasks {
    pub fn spawn(
        &mut self,
        name: &'static str,
        task: impl Future<Output = anyhow::Result<()>> + Send + 'static,
    ) {
        let id = self.set.spawn(task).id();
        self.names.insert(id, name);
    }

    /// The name of a task that ended (forgotten: `names` holds the running ones).
    fn name(&mut self, id: tokio::task::Id) -> &'static str {
        self.names.remove(&id).unwrap_or("unnamed")
    }

    /// Waits for the first task to end (never, while all run) and says which and how: before
    /// the stop, any end is a failure.
    pub async fn first_end(&mut self) -> anyhow::Error {
        match self.set.join_next_with_id().await {
            None => std::future::pending().await,
            Some(Ok((id, Ok(())))) => anyhow::anyhow!(
                "the {} task ended while the service was running",
                self.name(id)
            ),
            Some(Ok((id, Err(e)))) => e.context(format!("the {} task failed", self.name(id))),
            Some(Err(e)) => anyhow::anyhow!("the {} task {}", self.name(e.id()), join_error(&e)),
        }
    }

    /// After the stop: waits up to `grace` for every task, then aborts the rest (logged by name).
    /// Returns the names of the aborted ones, or the first failure of a task that ended within
    /// the grace.
    pub async fn finish(mut self, grace: Duration) -> anyhow::Result<Vec<&'static str>> {
        let deadline = Instant::now() + grace;
        let mut first_error = None;
        let mut dropped = Vec::new();
        loop {
            match tokio::time::timeout_at(deadline, self.set.join_next_with_id()).await {
                Ok(None) => break,
                Ok(Some(Ok((id, Ok(()))))) => {
                    self.name(id);
                }
                Ok(Some(Ok((id, Err(e))))) => {
                    let e = e.context(format!("the {} task failed", self.name(id)));
                    tracing::error!("{e:#}");
                    first_error.get_or_insert(e);
                }
                Ok(Some(Err(e))) => {
                    let e = anyhow::anyhow!("the {} task {}", self.name(e.id()), join_error(&e));
                    tracing::error!("{e:#}");
                    first_error.get_or_insert(e);
                }
                Err(_) => {
                    dropped = self.names.values().copied().collect();
                    dropped.sort_unstable();
                    tracing::warn!(
                        "stopping: {} still busy after {} s, dropped",
                        dropped.join(", "),
                        grace.as_secs_f64()
                    );
                    self.set.shutdown().await;
                    break;
                }
            }
        }
        first_error.map_or(Ok(dropped), Err)
    }
}

fn join_error(e: &tokio::task::JoinError) -> String {
    if e.is_cancelled() {
        return "was cancelled".into();
    }
    match e {
        e if e.is_panic() => "panicked".into(),
        e => format!("failed: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_task_that_ends_or_fails_while_serving_is_named() {
        let mut tasks = Tasks::default();
        tasks.spawn("forever", std::future::pending());
        tasks.spawn("quitter", async { Ok(()) });
        let err = tasks.first_end().await;
        assert_eq!(
            err.to_string(),
            "the quitter task ended while the service was running"
        );
        tasks.spawn("failing", async { Err(anyhow::anyhow!("disk on fire")) });
        let err = tasks.first_end().await;
        assert_eq!(format!("{err:#}"), "the failing task failed: disk on fire");
        tasks.spawn("panicking", async { panic!("boom") });
        let err = tasks.first_end().await;
        assert_eq!(err.to_string(), "the panicking task panicked");
    }

    #[tokio::test]
    async fn a_stop_waits_for_the_tasks_at_most_the_grace() {
        let mut tasks = Tasks::default();
        tasks.spawn("forever", std::future::pending());
        tasks.spawn("done", async { Ok(()) });
        let t0 = std::time::Instant::now();
        let dropped = tasks.finish(Duration::from_millis(200)).await.unwrap();
        assert_eq!(dropped, ["forever"]);
        let waited = t0.elapsed();
        assert!(
            waited >= Duration::from_millis(200) && waited < Duration::from_secs(2),
            "{waited:?}"
        );
        // A task that fails while stopping makes the stop an error that names it.
        let mut tasks = Tasks::default();
        tasks.spawn("gRPC server", async {
            Err(anyhow::anyhow!("accept failed"))
        });
        let err = tasks.finish(Duration::from_secs(1)).await.unwrap_err();
        assert!(format!("{err:#}").contains("gRPC server"), "{err:#}");
    }
}
