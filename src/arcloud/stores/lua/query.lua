-- Objects indexed in some cells, with their bounds, in one round trip.
-- KEYS[1]: the map's bounds HASH. ARGV[1]: the map prefix, ARGV[2..]: cell names "i:j:k".
-- Returns a flat list id1, bounds1, id2, bounds2, ... (bounds: 6 packed float64).
local BATCH = 1000  -- keep unpack() below Lua's stack limit
local prefix = ARGV[1]
local ids = {}
local seen = {}
for first = 2, #ARGV, BATCH do
  local cell_keys = {}
  for i = first, math.min(first + BATCH - 1, #ARGV) do
    cell_keys[#cell_keys + 1] = prefix .. ':cell:' .. ARGV[i]
  end
  for _, id in ipairs(redis.call('SUNION', unpack(cell_keys))) do
    if not seen[id] then
      seen[id] = true
      ids[#ids + 1] = id
    end
  end
end
local out = {}
for first = 1, #ids, BATCH do
  local batch = {}
  for i = first, math.min(first + BATCH - 1, #ids) do
    batch[#batch + 1] = ids[i]
  end
  local bounds = redis.call('HMGET', KEYS[1], unpack(batch))
  for i, id in ipairs(batch) do
    if bounds[i] then
      out[#out + 1] = id
      out[#out + 1] = bounds[i]
    end
  end
end
return out
