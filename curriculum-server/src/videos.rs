//! Eval videos sent by eval actors (`rfcl.v1.EvalVideos.Put`): kept as files in `RUN_DIR/videos/`,
//! listed in the dashboard's view and served at `/videos/<name>`. The file name carries what a
//! video shows ([`VideoMeta::file_name`]), so a restarted server lists its videos again from the
//! directory alone.
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use rfcl_core::video::{EvalVideo, VideoMeta};
use rfcl_proto::v1;
use tonic::{Request, Response, Status};

/// The most videos one run keeps; later ones are refused and counted (a run records one every
/// `eval_env.video_every` evaluations, far fewer than this).
pub const MAX_VIDEOS: usize = 1000;

/// The videos of a run, on disk.
#[derive(Debug)]
pub struct VideoStore {
    /// `RUN_DIR/videos`; `None` for a server without a run directory, which keeps none.
    dir: Option<PathBuf>,
    index: Mutex<Vec<VideoMeta>>,
    /// Videos refused: no run directory, over [`MAX_VIDEOS`], or a failed write.
    refused: AtomicU64,
}

/// The counts the dashboard shows beside the links.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoListing {
    pub videos: Vec<VideoMeta>,
    pub refused: u64,
}

impl VideoStore {
    /// The store of `run_dir`, with the videos already there (a restarted server).
    pub fn open(run_dir: Option<PathBuf>) -> std::io::Result<VideoStore> {
        let dir = run_dir.map(|d| d.join("videos"));
        let mut index = Vec::new();
        if let Some(dir) = dir.as_ref().filter(|d| d.is_dir()) {
            for entry in std::fs::read_dir(dir)? {
                let name = entry?.file_name();
                if let Some(meta) = name.to_str().and_then(VideoMeta::from_file_name) {
                    index.push(meta);
                }
            }
        }
        index.sort_by_key(|m| (m.policy_version, m.file_name()));
        Ok(VideoStore {
            dir,
            index: Mutex::new(index),
            refused: AtomicU64::new(0),
        })
    }

    /// Keeps a video; its name. The same episode sent again replaces its file.
    pub fn put(&self, video: EvalVideo) -> Result<String, Status> {
        let refuse = |status: Status| {
            self.refused.fetch_add(1, Ordering::Relaxed);
            Err(status)
        };
        let Some(dir) = &self.dir else {
            return refuse(Status::failed_precondition(
                "this curriculum server has no run directory to keep eval videos in",
            ));
        };
        let name = video.meta.file_name();
        let mut index = self.index.lock().unwrap_or_else(|p| p.into_inner());
        let known = index.iter().any(|m| m.file_name() == name);
        if !known && index.len() >= MAX_VIDEOS {
            return refuse(Status::resource_exhausted(format!(
                "this run keeps at most {MAX_VIDEOS} eval videos"
            )));
        }
        let written = std::fs::create_dir_all(dir)
            .and_then(|()| rfcl_core::atomic::atomic_write(&dir.join(&name), &video.gif));
        if let Err(e) = written {
            return refuse(Status::internal(format!(
                "writing {}: {e}",
                dir.join(&name).display()
            )));
        }
        if !known {
            index.push(video.meta);
            index.sort_by_key(|m| (m.policy_version, m.file_name()));
        }
        Ok(name)
    }

    pub fn listing(&self) -> VideoListing {
        VideoListing {
            videos: self.index.lock().unwrap_or_else(|p| p.into_inner()).clone(),
            refused: self.refused.load(Ordering::Relaxed),
        }
    }

    /// The bytes of a kept video; `None` for any name the store does not list (so no path a
    /// client makes up is ever opened).
    pub fn read(&self, name: &str) -> Option<Vec<u8>> {
        let listed = self
            .index
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .any(|m| m.file_name() == name);
        listed
            .then(|| std::fs::read(self.dir.as_ref()?.join(name)).ok())
            .flatten()
    }
}

/// The tonic service.
pub struct EvalVideosService {
    pub store: std::sync::Arc<VideoStore>,
}

#[tonic::async_trait]
impl v1::eval_videos_server::EvalVideos for EvalVideosService {
    async fn put(
        &self,
        request: Request<v1::EvalVideo>,
    ) -> Result<Response<v1::EvalVideoAck>, Status> {
        let video = rfcl_proto::convert::eval_video(request.into_inner()).inspect_err(|_| {
            self.store.refused.fetch_add(1, Ordering::Relaxed);
        })?;
        let store = self.store.clone();
        let name = tokio::task::spawn_blocking(move || store.put(video))
            .await
            .map_err(|e| Status::internal(format!("writing the video: {e}")))??;
        Ok(Response::new(v1::EvalVideoAck { name }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn video(version: u64, success: bool) -> EvalVideo {
        EvalVideo {
            meta: VideoMeta {
                policy_version: version,
                env_steps: version * 1000,
                seed: 1_000_000 + version,
                success_at_end: success,
                episode_return: 3.0,
                actor_id: 2,
            },
            gif: format!("GIF89a video {version}").into_bytes(),
        }
    }

    #[test]
    fn videos_are_kept_listed_served_and_found_again_after_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let store = VideoStore::open(Some(dir.path().into())).unwrap();
        let second = store.put(video(20, true)).unwrap();
        let first = store.put(video(10, false)).unwrap();
        // Sent again: replaced, not listed twice.
        assert_eq!(store.put(video(10, false)).unwrap(), first);
        let listing = store.listing();
        let versions: Vec<u64> = listing.videos.iter().map(|m| m.policy_version).collect();
        assert_eq!((versions, listing.refused), (vec![10, 20], 0));
        assert_eq!(store.read(&second).unwrap(), b"GIF89a video 20");
        // Only listed names are opened.
        std::fs::write(dir.path().join("videos/other.gif"), b"GIF89a").unwrap();
        assert_eq!(store.read("other.gif"), None);
        assert_eq!(store.read("../snapshot.json"), None);

        let again = VideoStore::open(Some(dir.path().into())).unwrap();
        assert_eq!(again.listing().videos, store.listing().videos);
        assert_eq!(again.read(&first).unwrap(), b"GIF89a video 10");
    }

    #[test]
    fn without_a_run_directory_videos_are_refused_and_counted() {
        let store = VideoStore::open(None).unwrap();
        let err = store.put(video(1, true)).unwrap_err();
        assert_eq!(err.code(), tonic::Code::FailedPrecondition);
        assert_eq!(store.listing().refused, 1);
    }
}
