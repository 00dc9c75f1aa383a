-- Accept a frame: record it and queue it in one step, so that no frame is recorded as accepted
-- without being queued (a crash between two writes once left frames "pending" for ever).
-- KEYS[1] the map's accepted SET, KEYS[2] its failed SET, KEYS[3] its frame status HASH,
-- KEYS[4] the ingest STREAM, KEYS[5] the stats HASH.
-- ARGV[1] the frame key, ARGV[2] the most frames queued, ARGV[3] the map id, ARGV[4] accepted_at_s,
-- ARGV[5] the encoded frame.
-- Returns the new entry id when queued, 0 for a duplicate, -1 when the stream is full.
-- A frame accepted before is a duplicate while its entry is in the stream (queued or pending) or it was
-- processed; one that failed, or whose entry is gone without an outcome (lost), is queued again.
local frame_key = ARGV[1]
if redis.call('SISMEMBER', KEYS[1], frame_key) == 1 and redis.call('SISMEMBER', KEYS[2], frame_key) == 0 then
  local status = redis.call('HGET', KEYS[3], frame_key)
  local settled_or_queued = false
  if status == 'processed' then
    settled_or_queued = true
  elseif status and string.sub(status, 1, 7) == 'queued ' then
    local entry_id = string.sub(status, 8)
    settled_or_queued = #redis.call('XRANGE', KEYS[4], entry_id, entry_id) > 0
  end
  if settled_or_queued then
    redis.call('HINCRBY', KEYS[5], 'duplicates', 1)
    return 0
  end
end
if redis.call('XLEN', KEYS[4]) >= tonumber(ARGV[2]) then return -1 end
local entry_id = redis.call('XADD', KEYS[4], '*', 'map_id', ARGV[3], 'frame_key', frame_key,
  'accepted_at_s', ARGV[4], 'frame', ARGV[5])
redis.call('SADD', KEYS[1], frame_key)
redis.call('SREM', KEYS[2], frame_key)
redis.call('HSET', KEYS[3], frame_key, 'queued ' .. entry_id)
redis.call('HINCRBY', KEYS[5], 'accepted', 1)
return entry_id
