-- Settle one delivery in one step: acknowledge and delete its entry, take its frame off the backlog,
-- count it, and (the first time the entry settles) write the frame's outcome: processed, or failed with a
-- dead letter. Only the call that deletes the entry takes it off the backlog, so two workers settling
-- one entry (a claimed frame whose slow worker finished too) count it once. Needs records.lua before it.
-- Every key is of the entry's ingest shard (its hash tag: one Cluster slot).
-- KEYS[1] the shard's STREAM, KEYS[2] its stats HASH, KEYS[3] its backlog HASH,
-- KEYS[4] the map's status HASH, KEYS[5] its sweep cursor, KEYS[6] its counts HASH,
-- KEYS[7] the shard's dead-letter STREAM, KEYS[8] its dead letters' bytes STRING.
-- ARGV[1] the consumer group, ARGV[2] the entry id, ARGV[3] the map id, ARGV[4] the frame key (both
-- as the entry carries them), ARGV[5] the entry's 'bytes' ('' when it has none: accepted before the
-- backlog was counted), ARGV[6] now (Unix s), ARGV[7] frame_record_retention_s, ARGV[8] records
-- looked at by the sweep, ARGV[9] JSON {"add": {stats field: integer}, "sums": {stats field: seconds}}
-- (counters, the histograms' buckets and sums), ARGV[10] 'processed', or 'failed' followed by ARGV[11]
-- the reason, ARGV[12] deliveries, ARGV[13] the consumer, ARGV[14] max_dead_letters,
-- ARGV[15] max_dead_letter_bytes (the shard's shares).
-- A frame's record is written only where it is still kept (not when its map was forgotten meanwhile).
-- Returns 1 when this call settled the entry, 0 when it was settled before (a failure is then not counted
-- again: two workers that gave one entry up count one failed frame).
local stream, stats, backlog = KEYS[1], KEYS[2], KEYS[3]
local status_key, sweep_key, counts_key = KEYS[4], KEYS[5], KEYS[6]
local dead_stream, dead_bytes = KEYS[7], KEYS[8]
local entry_id, map_id, frame_key, now = ARGV[2], ARGV[3], ARGV[4], ARGV[6]
local outcome = ARGV[10]

local dead = {}
if outcome == 'failed' then
  local found = redis.call('XRANGE', stream, entry_id, entry_id)
  if #found > 0 then
    dead = found[1][2]
  end
end
redis.call('XACK', stream, ARGV[1], entry_id)
local settled_now = redis.call('XDEL', stream, entry_id) == 1

if settled_now or outcome ~= 'failed' then
  local counters = cjson.decode(ARGV[9])
  for name, n in pairs(counters.add) do
    redis.call('HINCRBY', stats, name, n)
  end
  for name, seconds in pairs(counters.sums or {}) do
    redis.call('HINCRBYFLOAT', stats, name, seconds)
  end
end
if not settled_now then
  return 0
end

local function take_off(field, amount)
  if redis.call('HINCRBY', backlog, field, -amount) <= 0 then
    redis.call('HDEL', backlog, field)
  end
end
if ARGV[5] ~= '' then
  local n_bytes = tonumber(ARGV[5])
  take_off('frames', 1)
  take_off('bytes', n_bytes)
  take_off('frames:' .. map_id, 1)
  take_off('bytes:' .. map_id, n_bytes)
end

local record = 'processed ' .. now
if outcome == 'failed' then
  local payload = ''
  for i = 1, #dead, 2 do
    if dead[i] == 'frame' then
      payload = dead[i + 1]
    end
  end
  table.insert(dead, 'reason')
  table.insert(dead, ARGV[11])
  for _, pair in ipairs({{'entry_id', entry_id}, {'deliveries', ARGV[12]}, {'consumer', ARGV[13]}, {'failed_at_s', now}}) do
    table.insert(dead, pair[1])
    table.insert(dead, pair[2])
  end
  local dead_id = redis.call('XADD', dead_stream, '*', unpack(dead))
  redis.call('INCRBY', dead_bytes, #payload)
  -- The oldest dead letters go past either cap (a few a call: each call adds one).
  for _ = 1, 10 do
    local kept = redis.call('XLEN', dead_stream)
    if kept == 0 then
      redis.call('SET', dead_bytes, 0)
      break
    end
    if kept <= tonumber(ARGV[14]) and tonumber(redis.call('GET', dead_bytes)) <= tonumber(ARGV[15]) then
      break
    end
    local oldest = redis.call('XRANGE', dead_stream, '-', '+', 'COUNT', 1)[1]
    local oldest_fields = oldest[2]
    for i = 1, #oldest_fields, 2 do
      if oldest_fields[i] == 'frame' then
        redis.call('DECRBY', dead_bytes, #oldest_fields[i + 1])
      end
    end
    redis.call('XDEL', dead_stream, oldest[1])
  end
  record = 'failed ' .. now .. ' ' .. dead_id .. ' ' .. ARGV[12] .. ' ' .. ARGV[11]
end

if map_id ~= '' and frame_key ~= '' and redis.call('HEXISTS', status_key, frame_key) == 1 then
  local before = redis.call('HGET', status_key, frame_key)
  if outcome == 'failed' and string.sub(before, 1, 7) ~= 'failed ' then
    redis.call('HINCRBY', counts_key, 'failed', 1)
  end
  redis.call('HSET', status_key, frame_key, record)
  sweep(status_key, sweep_key, tonumber(now) - tonumber(ARGV[7]), tonumber(ARGV[8]), settled_at)
end
return 1
