"""agg.v1.JobService over the job store (``service.jobstore.JobStore`` protocol: ``get``, ``list``, ``events``,
``request_cancel``). Another tenant's job is NOT_FOUND; an unreachable Redis is UNAVAILABLE (grpc_common)."""

from __future__ import annotations

from worker.grpc_common import Auth, Code, RpcFailure, streaming, unary
from worker.grpc_convert import job_to_proto, to_struct
from worker.grpc_proto import job_pb2, job_pb2_grpc

TERMINAL = ("succeeded", "failed", "cancelled")


class JobServicer(job_pb2_grpc.JobServiceServicer):
    """``poll_ms``: how long one blocking read of the event stream waits before the job state is re-checked."""

    def __init__(self, auth: Auth, jobs, poll_ms: int = 1000):
        self.auth, self.jobs, self.poll_ms = auth, jobs, int(poll_ms)

    def _own(self, job_id: str, tenant: str) -> dict:
        job = self.jobs.get(job_id) if isinstance(job_id, str) and job_id else None
        if job is None or job.get("tenant") != tenant:
            raise RpcFailure(Code.NOT_FOUND, "job not found")
        return job

    @unary
    def GetJob(self, request, context):  # noqa: N802
        return job_to_proto(self._own(request.job_id, self.auth.tenant(context, "read")))

    @unary
    def ListJobs(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "read")
        return job_pb2.ListJobsResponse(jobs=[job_to_proto(j) for j in self.jobs.list(tenant)
                                              if j.get("tenant", tenant) == tenant])

    @streaming
    def WatchJob(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "read")
        job_id = request.job_id
        job = self._own(job_id, tenant)
        after = request.after_event_id or None
        while context.is_active():
            done = job.get("state") in TERMINAL
            block = self.poll_ms if request.follow and not done else 0
            try:
                events = self.jobs.events(job_id, after, block)
            except ValueError:
                raise RpcFailure(Code.INVALID_ARGUMENT, f"malformed after_event_id {after!r} (want an event_id "
                                                        "received from WatchJob, e.g. '1718000000000-0')") from None
            if events:
                job = self.jobs.get(job_id) or job
                snapshot = job_to_proto(job)
                for event_id, event in events:
                    yield job_pb2.JobEvent(event_id=event_id, event=to_struct(event), job=snapshot)
                    after = event_id
                continue
            if done or not request.follow:
                return
            job = self.jobs.get(job_id) or job

    @unary
    def CancelJob(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "cancel")
        job = self._own(request.job_id, tenant)
        if not self.jobs.request_cancel(request.job_id):
            job = self.jobs.get(request.job_id) or job
            raise RpcFailure(Code.FAILED_PRECONDITION, f"the job already ended ({job.get('state')})")
        return job_pb2.CancelJobResponse(job=job_to_proto(self.jobs.get(request.job_id) or job))
