"""Lua scripts of the job store: each state change is one atomic script run inside Redis.

Every script reads the clock with ``TIME`` (the Redis server's clock), so leases never depend on the clocks of
the machines that run workers. Every transition appends a JSON entry to the job's history list and an event to
its bounded stream (``XADD ... MAXLEN ~ n``). A worker's writes are fenced by ``attempt``: a write from an
attempt that is no longer the current one changes nothing (it returns 'lost').

KEYS/ARGV conventions are documented per script; ``E`` below is the events stream key.
"""

COMMON = r"""
local function now()
  local t = redis.call('TIME')
  return tonumber(t[1]) + tonumber(t[2]) / 1000000
end
local function fmt(x) return string.format('%.6f', x) end
local function event(stream, maxlen, ev)
  return redis.call('XADD', stream, 'MAXLEN', '~', maxlen, '*', 'data', cjson.encode(ev))
end
local function history(key, entry) redis.call('RPUSH', key, cjson.encode(entry)) end
"""

# KEYS: job, history, E, leases   ARGV: job_id, attempt, worker, lease_s, maxlen
START = COMMON + r"""
local st = redis.call('HGET', KEYS[1], 'state')
if not st then return 'missing' end
if st ~= 'queued' then return st end
if redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[2] then return 'lost' end
local t = now()
local lease = t + tonumber(ARGV[4])
redis.call('HSET', KEYS[1], 'state', 'running', 'worker', ARGV[3], 'lease_until', fmt(lease),
           'updated_at', fmt(t))
if not redis.call('HGET', KEYS[1], 'started_at') then redis.call('HSET', KEYS[1], 'started_at', fmt(t)) end
redis.call('ZADD', KEYS[4], lease, ARGV[1])
local a = tonumber(ARGV[2])
history(KEYS[2], {state='running', at=t, worker=ARGV[3], attempt=a})
event(KEYS[3], ARGV[5], {type='state', state='running', at=t, worker=ARGV[3], attempt=a,
      progress=tonumber(redis.call('HGET', KEYS[1], 'progress') or '0')})
return 'ok'
"""

# KEYS: job, leases   ARGV: job_id, attempt, lease_s  ->  'run' | 'cancel' | 'lost'
RENEW = COMMON + r"""
if redis.call('HGET', KEYS[1], 'state') ~= 'running' or redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[2] then
  return 'lost'
end
local lease = now() + tonumber(ARGV[3])
redis.call('HSET', KEYS[1], 'lease_until', fmt(lease))
redis.call('ZADD', KEYS[2], lease, ARGV[1])
if redis.call('HGET', KEYS[1], 'cancel_requested') == '1' then return 'cancel' end
return 'run'
"""

# KEYS: job, E   ARGV: attempt, progress, event_json, maxlen  ->  'ok' | 'lost'
PROGRESS = COMMON + r"""
if redis.call('HGET', KEYS[1], 'state') ~= 'running' or redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[1] then
  return 'lost'
end
local t = now()
local p = math.max(tonumber(redis.call('HGET', KEYS[1], 'progress') or '0'), tonumber(ARGV[2]))
local ev = cjson.decode(ARGV[3])
ev.type = 'progress'; ev.at = t; ev.progress = p; ev.attempt = tonumber(ARGV[1])
redis.call('HSET', KEYS[1], 'progress', string.format('%.6f', p), 'updated_at', fmt(t),
           'phase', tostring(ev.phase or ''), 'iteration', tostring(ev.iteration or ''),
           'total', tostring(ev.total or ''))
event(KEYS[2], ARGV[4], ev)
return 'ok'
"""

# KEYS: job, history, E, leases, tenant_active   ARGV: job_id, attempt, state, worker, fields_json, maxlen, ttl
FINISH = COMMON + r"""
local st = redis.call('HGET', KEYS[1], 'state')
if st ~= 'running' or redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[2] then return 'lost' end
local t = now()
local f = cjson.decode(ARGV[5])
redis.call('HSET', KEYS[1], 'state', ARGV[3], 'finished_at', fmt(t), 'updated_at', fmt(t), 'lease_until', '')
for k, v in pairs(f) do redis.call('HSET', KEYS[1], k, v) end
if ARGV[3] == 'succeeded' then redis.call('HSET', KEYS[1], 'progress', '1.000000') end
redis.call('ZREM', KEYS[4], ARGV[1])
redis.call('SREM', KEYS[5], ARGV[1])
local a = tonumber(ARGV[2])
history(KEYS[2], {state=ARGV[3], at=t, worker=ARGV[4], attempt=a, reason=(f.error ~= '' and f.error or nil)})
event(KEYS[3], ARGV[6], {type='state', state=ARGV[3], at=t, worker=ARGV[4], attempt=a, error=f.error,
      scene_id=redis.call('HGET', KEYS[1], 'scene_id'),
      progress=tonumber(redis.call('HGET', KEYS[1], 'progress') or '0')})
local ttl = tonumber(ARGV[7])
if ttl > 0 then
  redis.call('EXPIRE', KEYS[1], ttl); redis.call('EXPIRE', KEYS[2], ttl); redis.call('EXPIRE', KEYS[3], ttl)
end
return 'ok'
"""

# KEYS: job, history, E, tenant_active   ARGV: job_id, who, maxlen, ttl  ->  'cancelled_now' | 'cancelling' | state
CANCEL = COMMON + r"""
local st = redis.call('HGET', KEYS[1], 'state')
if not st then return 'missing' end
local t = now()
if st == 'queued' then
  redis.call('HSET', KEYS[1], 'state', 'cancelled', 'finished_at', fmt(t), 'updated_at', fmt(t),
             'cancel_requested', '1', 'error', 'cancelled by ' .. ARGV[2])
  redis.call('SREM', KEYS[4], ARGV[1])
  history(KEYS[2], {state='cancelled', at=t, worker='', attempt=tonumber(redis.call('HGET', KEYS[1], 'attempt')),
          reason='cancelled while queued'})
  event(KEYS[3], ARGV[3], {type='state', state='cancelled', at=t,
        progress=tonumber(redis.call('HGET', KEYS[1], 'progress') or '0')})
  local ttl = tonumber(ARGV[4])
  if ttl > 0 then
    redis.call('EXPIRE', KEYS[1], ttl); redis.call('EXPIRE', KEYS[2], ttl); redis.call('EXPIRE', KEYS[3], ttl)
  end
  return 'cancelled_now'
end
if st == 'running' then
  if redis.call('HGET', KEYS[1], 'cancel_requested') ~= '1' then
    redis.call('HSET', KEYS[1], 'cancel_requested', '1', 'updated_at', fmt(t))
    event(KEYS[3], ARGV[3], {type='cancel_requested', state='running', at=t})
  end
  return 'cancelling'
end
return st
"""
