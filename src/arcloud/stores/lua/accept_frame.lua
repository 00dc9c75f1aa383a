-- Accept a frame: record it, count it and queue it in one step, so that no frame is recorded as accepted
-- without being queued (a crash between two writes once left frames "pending" for ever) and the backlog
-- counters are always the sum of what the stream holds (settle_frame.lua takes frames off).
-- Needs records.lua before it. Every key is of the map's ingest shard (its hash tag: one Cluster slot).
-- KEYS[1] the map's status HASH, KEYS[2] its sweep cursor, KEYS[3] its counts HASH,
-- KEYS[4] the shard's STREAM, KEYS[5] its stats HASH, KEYS[6] its backlog HASH.
-- ARGV[1] the frame key, ARGV[2] the map id, ARGV[3] now (Unix s), ARGV[4] the encoded frame,
-- ARGV[5] frame_record_retention_s, ARGV[6] records looked at by the sweep,
-- ARGV[7..10] max_queued_frames, max_queued_bytes (the shard's share of both), max_queued_frames_per_map,
-- max_queued_bytes_per_map.
-- Returns the new entry id when queued, 0 for a duplicate, or {limit, held, frame bytes} when the
-- limit (a QueueLimits field) refuses the frame (QueueLimits.refusal checks the same, in the same order).
-- A frame accepted before is a duplicate while its entry is in the stream (queued or pending) or it was
-- processed; one that failed, or whose entry is gone without an outcome (lost), is queued again. A
-- record of a frame settled longer than the retention ago counts as gone (the sweep drops such records):
-- the frame is a new one.
local status_key, sweep_key, counts_key = KEYS[1], KEYS[2], KEYS[3]
local stream, stats, backlog = KEYS[4], KEYS[5], KEYS[6]
local frame_key, map_id, payload = ARGV[1], ARGV[2], ARGV[4]
local cutoff = tonumber(ARGV[3]) - tonumber(ARGV[5])

sweep(status_key, sweep_key, cutoff, tonumber(ARGV[6]), settled_at)
local status = redis.call('HGET', status_key, frame_key)
if status then
  local at = settled_at(status)
  if at and at < cutoff then
    redis.call('HDEL', status_key, frame_key)
    status = false
  end
end
local duplicate = false
if status and string.sub(status, 1, 10) == 'processed ' then
  duplicate = true
elseif status and string.sub(status, 1, 7) == 'queued ' then
  local entry_id = string.sub(status, 8)
  duplicate = #redis.call('XRANGE', stream, entry_id, entry_id) > 0
end
if duplicate then
  redis.call('HINCRBY', stats, 'duplicates', 1)
  return 0
end

local n_bytes = #payload
local held = redis.call('HMGET', backlog, 'frames', 'bytes', 'frames:' .. map_id, 'bytes:' .. map_id)
local limits = {'max_queued_frames', 'max_queued_bytes', 'max_queued_frames_per_map', 'max_queued_bytes_per_map'}
local adding = {1, n_bytes, 1, n_bytes}
for i = 1, 4 do
  local now_held = tonumber(held[i] or 0)
  if now_held + adding[i] > tonumber(ARGV[6 + i]) then
    return {limits[i], now_held, n_bytes}
  end
end

local entry_id = redis.call('XADD', stream, '*', 'map_id', map_id, 'frame_key', frame_key,
  'accepted_at_s', ARGV[3], 'bytes', n_bytes, 'frame', payload)
redis.call('HINCRBY', backlog, 'frames', 1)
redis.call('HINCRBY', backlog, 'bytes', n_bytes)
redis.call('HINCRBY', backlog, 'frames:' .. map_id, 1)
redis.call('HINCRBY', backlog, 'bytes:' .. map_id, n_bytes)
if not status then
  redis.call('HINCRBY', counts_key, 'accepted', 1)
elseif string.sub(status, 1, 7) == 'failed ' and tonumber(redis.call('HGET', counts_key, 'failed') or 0) > 0 then
  redis.call('HINCRBY', counts_key, 'failed', -1)
end
redis.call('HSET', status_key, frame_key, 'queued ' .. entry_id)
redis.call('HINCRBY', stats, 'accepted', 1)
return entry_id
